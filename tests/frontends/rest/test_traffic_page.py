"""The traffic and scan page (``GET /traffic``, docs/dashboard.md) in a real headless
Chromium against a gateway process on simulated sensors: the traffic table shows the
line's frames and stops adding rows while paused; a scan of a free port lists the
sensor, and its Add button fills the YAML snippet."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from test_dashboard import (
    FAST,
    bus,
    chromium,
    console_errors,
    gateway,
    get_json,
    log_in,
    screenshot,
    wait,
)
from test_setup_scan import scan_end

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

TOKEN = "t0ken-for-the-traffic-page"
ROWS_JS = "return [...document.querySelectorAll('#frames tr')].map(r => r.textContent)"


def rows(driver: Any) -> list[str]:
    value = driver.execute_script(ROWS_JS)
    assert isinstance(value, list)
    return value


def test_the_traffic_page_shows_frames_pauses_and_the_scan_finds_a_sensor(
        tmp_path: Path) -> None:
    polled = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    target = make_sensor(WireProtocol.NATIVE, Series.VG, 9, baud=FAST)
    with simulated([polled]) as used, simulated([target]) as free:
        cfg = {"gateway_id": "page", "http": {"token": TOKEN},
               "buses": [bus("a", used.path, "native",
                             [{"name": "boom", "series": "AH", "poll_hz": 10}])]}
        with gateway(tmp_path, cfg, TOKEN) as base, chromium(tmp_path) as driver:
            log_in(driver, base, "", TOKEN, "admin")  # (http.token is an admin's)
            driver.find_element("css selector", 'a[href="traffic"]').click()
            wait(lambda: len(rows(driver)) >= 5, "five frames in the table")
            assert all("77 04 00 59 5D" in r and "boom" in r for r in rows(driver)[:5])
            driver.find_element("id", "pause").click()
            # (a frame may be on its way as the button is clicked: the count after one)
            wait(lambda: "paused (" in driver.find_element("id", "traffic-state").text,
                 "the page counts frames it does not show")
            held = len(rows(driver))
            wait(lambda: int(driver.find_element("id", "traffic-state").text
                             .split("(")[1].split()[0]) >= 5, "five frames held back")
            assert len(rows(driver)) == held
            driver.find_element("id", "pause").click()
            wait(lambda: any("came while paused" in r for r in rows(driver)),
                 "the page says what came while paused")

            driver.find_element("id", "scan-port").send_keys(free.path)
            driver.find_element("id", "scan-modbus").click()  # native only
            bauds = driver.find_element("id", "scan-bauds")
            bauds.clear()
            bauds.send_keys(str(FAST))
            driver.find_element("id", "scan-start").click()
            try:
                ended = wait(lambda: scan_end(driver), "the scan ends", timeout=60)
            except AssertionError as exc:  # (what the scan was doing: its log, REST's)
                try:
                    scans = get_json(f"{base}/api/v1/scan", TOKEN)
                except Exception as error:  # (a gateway that hangs: the timeout first)
                    scans = f"no answer: {error!r}"
                raise AssertionError(
                    f"{exc}; the page: {driver.find_element('id', 'scan-state').text!r}; "
                    f"GET /api/v1/scan: {scans}") from None
            assert ended.startswith("done"), ended
            found = driver.find_element("id", "scan-found").text
            assert "native 115200 baud, address 9, series VG or MINS" in found
            driver.find_element("css selector", "#scan-found button").click()
            snippet = driver.find_element("id", "scan-snippet").get_attribute("value")
            screenshot(driver, tmp_path, "traffic-page.png")
            assert console_errors(driver) == []
    assert f"port: {free.path}" in snippet and "address: 9" in snippet
    assert "series: VG" in snippet and "baudrate: 115200" in snippet
