"""The Setup page (docs/dashboard.md, "Setup") in a real headless Chromium, with real
clicks and typing, against ``python -m imu_gateway run`` on simulated sensors, its
config in a real file: an admin adds a sensor in the form, sees the preview and applies
it, and the sensor is live; a broken value is shown beside its field and nothing
changes; the YAML tab applies a change too, its secret kept; a viewer has no Setup
link, and the config routes refuse them.  Waits are deadlines on a condition."""

from __future__ import annotations

import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from selenium.webdriver.common.keys import Keys
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

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

ADMIN = "setup-admin-t0ken"  # http.token: an admin's, shown as *** by the gateway
VIEWER = "setup-viewer-t0ken"
API = "/api/v1"


@pytest.fixture
def line() -> Iterator[str]:
    """Two simulated AH sensors on one line; the config names only the first."""
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    spare = make_sensor(WireProtocol.NATIVE, Series.AH, 1, baud=FAST)
    with simulated([boom, spare]) as sim:
        yield sim.path


def config(port: str) -> dict[str, Any]:
    return {"gateway_id": "setup",
            "buses": [bus("line", port, "native", [{"name": "boom", "series": "AH"}])],
            "http": {"token": ADMIN, "tokens": [{"token": VIEWER, "role": "viewer"}]}}


def status(method: str, url: str, token: str, body: bytes | None = None) -> int:
    request = urllib.request.Request(url, data=body, method=method,
                                     headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return int(response.status)
    except urllib.error.HTTPError as exc:
        return exc.code


def names(base: str) -> list[str]:
    return [s["name"] for s in get_json(f"{base}{API}/sensors")]


def has_reading(base: str, sensor: str) -> bool:
    try:
        return bool(get_json(f"{base}{API}/sensors/{sensor}/reading")["angles"])
    except urllib.error.HTTPError:
        return False  # 503: no reading yet


def page_state(driver: Any) -> str:
    return str(driver.execute_script("return document.body.dataset.state || ''"))


def field(driver: Any, path: str) -> Any:
    """The input (or select) of the field at this YAML path."""
    return driver.find_element("css selector", f'[data-path="{path}"] > input, '
                                               f'[data-path="{path}"] > select')


def error_beside(driver: Any, path: str) -> str:
    return str(driver.find_element("css selector", f'[data-path="{path}"] > .error').text)


def open_setup(driver: Any, base: str) -> None:
    """Log in as an admin on the dashboard, then follow its Setup link."""
    log_in(driver, base, "", ADMIN, "admin")
    link = driver.find_element("id", "setup-link")
    wait(link.is_displayed, "the Setup link is shown to an admin")
    link.click()
    wait(lambda: page_state(driver) == "editing", "the Setup page has the config")


def retype(element: Any, text: str) -> None:
    element.send_keys(Keys.CONTROL, "a")
    element.send_keys(Keys.DELETE)
    element.send_keys(text)


def test_an_admin_adds_a_sensor_in_the_form_previews_and_applies_it(
        tmp_path: Path, line: str) -> None:
    with gateway(tmp_path, config(line)) as base, chromium(tmp_path) as driver:
        open_setup(driver, base)
        help_text = driver.find_element("css selector", '[data-path="buses[0].baudrate"] .help')
        assert "9600 is the sensors' factory rate" in help_text.text  # the reference's text
        driver.find_element("css selector", '[data-add="buses[0].sensors"]').click()
        field(driver, "buses[0].sensors[1].name").send_keys("boom2")
        field(driver, "buses[0].sensors[1].series").send_keys("AH")
        field(driver, "buses[0].sensors[1].address").send_keys("1")
        driver.find_element("id", "preview").click()
        wait(lambda: page_state(driver) == "previewed", "the preview")
        shown = driver.find_element("id", "diff-list").text
        assert "sensors added: boom2 on line" in shown, shown
        assert "buses rescheduled (their port kept open): line" in shown, shown
        assert names(base) == ["boom"]  # a preview applies nothing
        screenshot(driver, tmp_path, "setup-preview.png")
        driver.find_element("id", "apply").click()
        wait(lambda: page_state(driver) == "applied", "applied")
        said = driver.find_element("id", "result").text
        assert said.startswith("applied: +1 sensor (boom2 on line") and "saved to" in said, said
        assert names(base) == ["boom", "boom2"]
        wait(lambda: has_reading(base, "boom2"), "boom2 reads from the simulator")
        # The form shows the config as it is now, the new sensor in it.
        assert field(driver, "buses[0].sensors[1].name").get_attribute("value") == "boom2"
        assert console_errors(driver) == []
    saved = (tmp_path / "gateway.yaml").read_text()
    assert "boom2" in saved and ADMIN in saved


def test_a_broken_value_shows_beside_its_field_and_changes_nothing(
        tmp_path: Path, line: str) -> None:
    with gateway(tmp_path, config(line)) as base, chromium(tmp_path) as driver:
        before = (tmp_path / "gateway.yaml").read_text()
        open_setup(driver, base)
        retype(field(driver, "buses[0].baudrate"), "fast")
        retype(field(driver, "buses[0].sensors[0].series"), "XY")
        driver.find_element("id", "preview").click()
        wait(lambda: page_state(driver) == "invalid", "the gateway's problems")
        assert error_beside(driver, "buses[0].baudrate") == \
            'must be a whole number, not "fast"'
        assert error_beside(driver, "buses[0].sensors[0].series").startswith(
            "must be one of IMU, VG, AH, MINS")
        assert error_beside(driver, "buses[0].port") == ""
        assert driver.find_element("id", "result").text == \
            "the config has 2 problems; nothing changed"
        assert not driver.find_element("id", "apply").is_enabled()
        screenshot(driver, tmp_path, "setup-problems.png")
        shown = get_json(f"{base}{API}/config", ADMIN)["config"]["buses"][0]
        assert shown["baudrate"] == FAST and shown["sensors"][0]["series"] == "AH"
        assert has_reading(base, "boom")
    assert (tmp_path / "gateway.yaml").read_text() == before


def test_the_yaml_tab_applies_a_change_and_keeps_the_hidden_secret(
        tmp_path: Path, line: str) -> None:
    with gateway(tmp_path, config(line)) as base, chromium(tmp_path) as driver:
        open_setup(driver, base)
        driver.find_element("id", "tab-yaml").click()
        editor = driver.find_element("id", "yaml")
        text = str(editor.get_attribute("value"))
        assert "token: '***'" in text and ADMIN not in text  # the secret stays hidden
        one = "  - name: boom\n    series: AH\n"
        assert one in text, text
        retype(editor, text.replace(one, one + "  - name: boom2\n    series: AH\n"
                                              "    address: 1\n"))
        driver.find_element("id", "preview").click()
        wait(lambda: page_state(driver) == "previewed", "the preview")
        assert "sensors added: boom2 on line" in driver.find_element("id", "diff-list").text
        driver.find_element("id", "apply").click()
        wait(lambda: page_state(driver) == "applied", "applied")
        assert names(base) == ["boom", "boom2"]
        wait(lambda: has_reading(base, "boom2"), "boom2 reads from the simulator")
        assert status("GET", f"{base}{API}/config", ADMIN) == 200  # *** kept the token
    saved = (tmp_path / "gateway.yaml").read_text()
    assert f"token: {ADMIN}" in saved and "***" not in saved


def test_a_viewer_has_no_setup_link_and_the_config_routes_refuse_them(
        tmp_path: Path, line: str) -> None:
    with gateway(tmp_path, config(line)) as base, chromium(tmp_path) as driver:
        log_in(driver, base, "", VIEWER, "viewer")
        assert not driver.find_element("id", "setup-link").is_displayed()
        body = b"buses: []"
        assert status("GET", f"{base}{API}/config", VIEWER) == 403
        assert status("GET", f"{base}{API}/config?format=yaml", VIEWER) == 403
        assert status("PUT", f"{base}{API}/config?dry_run=1", VIEWER, body) == 403
        assert status("PUT", f"{base}{API}/config", VIEWER, body) == 403
        # The schema is the reference's, nothing of this gateway's: a viewer's.
        schema = get_json(f"{base}{API}/config/schema", VIEWER)
        assert "9600 is the sensors' factory rate" in \
            schema["$defs"]["BusConfig"]["properties"]["baudrate"]["description"]
        driver.get(base + "/setup")  # the page itself, opened by its address
        wait(lambda: page_state(driver) == "refused", "the page says it is an admin's")
        assert "the Setup page is an admin's" in driver.find_element("id", "banner").text
        assert names(base) == ["boom"]
