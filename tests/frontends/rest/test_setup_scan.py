"""The Setup page's scan and its two drafts (docs/dashboard.md, "Setup") in a real
headless Chromium, with real clicks, against ``python -m imu_gateway run`` on
simulated sensors: a scan of the bus's own port (its polling paused, after the page
said so) finds a sensor the config lacks, Add puts it into the form, the preview says
+1 sensor, Apply, and the sensor reads; and an edit of the form is carried into the
YAML tab, while an edit of the YAML is never dropped without asking.  Waits are
deadlines on a condition."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from test_dashboard import FAST, chromium, console_errors, gateway, get_json, screenshot, wait
from test_setup_page import (
    ADMIN,
    API,
    config,
    field,
    has_reading,
    line,
    names,
    open_setup,
    page_state,
    retype,
)

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

__all__ = ["line"]  # (the fixture, imported to be used here)


def scan_end(driver: Any) -> str | None:
    """The scan's last line, once it has one: done, failed or cancelled."""
    text = str(driver.find_element("id", "scan-state").text)
    return text if text.startswith(("done", "failed", "cancelled")) else None


def test_a_scan_on_the_setup_page_finds_a_sensor_add_preview_apply_and_it_reads(
        tmp_path: Path, line: str) -> None:
    with gateway(tmp_path, config(line)) as base, chromium(tmp_path) as driver:
        open_setup(driver, base)
        find = driver.find_element
        find("id", "scan-port").send_keys(line)  # the bus's own port
        find("id", "scan-modbus").click()  # native only
        retype(find("id", "scan-bauds"), str(FAST))
        retype(find("id", "scan-last"), "3")
        find("id", "scan-start").click()
        # Nothing stops before the page has said what stops, and for how long.
        confirm = find("id", "scan-confirm")
        wait(confirm.is_displayed, "the page asks before the bus pauses")
        warning = find("id", "scan-state").text
        assert "is bus line's port: its polling pauses for the scan" in warning, warning
        assert has_reading(base, "boom")
        confirm.click()
        ended = wait(lambda: scan_end(driver), "the scan ends", timeout=60)
        assert ended.startswith("done: 2 found"), (ended, find("id", "scan-found").text)
        assert "bus line resumed" in find("id", "scan-state").text
        spare = find("css selector", '#scan-found li[data-address="1"]')
        assert "native 115200 baud, address 1, series AH" in spare.text
        # Address 0 is boom: its Add says so and adds nothing.
        find("css selector", '#scan-found li[data-address="0"] .scan-add').click()
        assert find("id", "result").text == \
            f"address 0 on {line} is in the config already: boom"
        spare.find_element("css selector", ".scan-add").click()
        assert find("id", "result").text.startswith("ah1 added to bus line")
        assert field(driver, "buses[0].sensors[1].name").get_attribute("value") == "ah1"
        find("id", "preview").click()
        wait(lambda: page_state(driver) == "previewed", "the preview")
        summary = find("id", "diff-summary").text
        assert "+1 sensor (ah1 on line" in summary, summary
        assert "sensors added: ah1 on line" in find("id", "diff-list").text
        screenshot(driver, tmp_path, "setup-scan.png")
        find("id", "apply").click()
        wait(lambda: page_state(driver) == "applied", "applied")
        assert names(base) == ["boom", "ah1"]
        wait(lambda: has_reading(base, "ah1"), "ah1 reads from the simulator")
        # (the browser logs the gateway's 409, the question the page asked: no other)
        assert [e for e in console_errors(driver) if "/api/v1/scan - " not in e["message"]
                or "409" not in e["message"]] == []
    saved = (tmp_path / "gateway.yaml").read_text()
    assert "ah1" in saved


def test_a_scan_of_a_port_no_bus_has_adds_a_new_bus(tmp_path: Path, line: str) -> None:
    other = make_sensor(WireProtocol.NATIVE, Series.VG, 9, baud=FAST)
    with simulated([other]) as free, gateway(tmp_path, config(line)) as base, \
            chromium(tmp_path) as driver:
        open_setup(driver, base)
        find = driver.find_element
        find("id", "scan-port").send_keys(free.path)
        find("id", "scan-modbus").click()
        retype(find("id", "scan-bauds"), str(FAST))
        find("id", "scan-start").click()
        ended = wait(lambda: scan_end(driver), "the scan ends", timeout=60)
        assert ended.startswith("done: 1 found"), (ended, find("id", "scan-found").text)
        find("css selector", "#scan-found .scan-add").click()
        assert field(driver, "buses[1].port").get_attribute("value") == free.path
        assert field(driver, "buses[1].baudrate").get_attribute("value") == str(FAST)
        assert field(driver, "buses[1].sensors[0].name").get_attribute("value") == "vg9"
        find("id", "preview").click()
        wait(lambda: page_state(driver) == "previewed", "the preview")
        assert "buses added: line-vg9" in find("id", "diff-list").text
        find("id", "apply").click()
        wait(lambda: page_state(driver) == "applied", "applied")
        wait(lambda: has_reading(base, "vg9"), "vg9 reads from the other line")


def test_the_form_and_the_yaml_tab_lose_no_draft(tmp_path: Path, line: str) -> None:
    with gateway(tmp_path, config(line)) as base, chromium(tmp_path) as driver:
        open_setup(driver, base)
        find = driver.find_element
        # A form edit, then the YAML tab: the edit is in the text.
        retype(field(driver, "buses[0].sensors[0].poll_hz"), "7")
        find("id", "tab-yaml").click()
        editor = find("id", "yaml")
        text = str(editor.get_attribute("value"))
        assert "    poll_hz: 7\n" in text, text
        assert "token: '***'" in text or 'token: "***"' in text, text
        # A YAML edit, then the form tab: the page asks, and keeps the YAML shown.
        one = "\n    series: AH\n"  # (as the gateway writes it: boom's)
        assert one in text, text
        retype(editor, text.replace(one, one + "    address: 0\n", 1) +
               "  # a comment\n")
        find("id", "tab-form").click()
        assert find("id", "switch-prompt").is_displayed()
        assert find("id", "yaml").is_displayed()
        assert not find("id", "form-view").is_displayed()
        find("id", "keep-yaml").click()
        assert not find("id", "switch-prompt").is_displayed()
        assert "# a comment" in str(find("id", "yaml").get_attribute("value"))
        # Preview and Apply from the YAML send both edits.
        find("id", "preview").click()
        wait(lambda: page_state(driver) == "previewed", "the preview")
        assert "sensors changed: boom (poll_hz" in find("id", "diff-list").text
        # Asked again, discarding goes back to the form's draft, its edit kept.
        find("id", "tab-form").click()
        find("id", "drop-yaml").click()
        assert find("id", "form-view").is_displayed()
        assert field(driver, "buses[0].sensors[0].poll_hz").get_attribute("value") == "7"
        find("id", "tab-yaml").click()
        assert "# a comment" not in str(find("id", "yaml").get_attribute("value"))
        find("id", "preview").click()
        wait(lambda: page_state(driver) == "previewed", "the preview")
        find("id", "apply").click()
        wait(lambda: page_state(driver) == "applied", "applied")
        shown = get_json(f"{base}{API}/config", ADMIN)["config"]["buses"][0]["sensors"][0]
        assert shown["poll_hz"] == 7
        assert console_errors(driver) == []
