"""The wizards page (docs/wizards.md, docs/dashboard.md) in a real headless Chromium, with
real clicks, against ``python -m imu_gateway run`` on a simulated AH sensor turned as a
person would turn it: the magnetic calibration reaches "done" with coverage 100 %, and
Save is offered and carried out.  Waits are deadlines on a condition."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
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
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

TOKEN = "wizard-page-token"
READING = Motion.from_seed(11).sample(2.0)

STATE_JS = """
return {state: document.body.dataset.state || null, step: document.body.dataset.step || null,
        coverage: document.getElementById("coverage").textContent,
        prompt: document.getElementById("prompt").textContent,
        points: Number(document.getElementById("plot").dataset.points || 0),
        save: !document.getElementById("save").hidden,
        result: document.getElementById("result").textContent};
"""


def shown(driver: Any) -> dict[str, Any]:
    value = driver.execute_script(STATE_JS)
    assert isinstance(value, dict)
    return value


def when(driver: Any, test: Callable[[dict[str, Any]], bool]) -> dict[str, Any] | None:
    """What the page shows, if it passes ``test``."""
    state = shown(driver)
    return state if test(state) else None


def test_the_magnetic_calibration_wizard_reaches_done_with_full_coverage(
        tmp_path: Path) -> None:
    compass = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([compass]) as sim:
        sim.call(compass.lean, 0.0, 0.0).result(5)
        sim.call(compass.turn, 0.0, 0.0, time.monotonic()).result(5)  # held, level
        cfg = {"gateway_id": "wiz", "buses": [bus("line", sim.path, "native", [
            {"name": "compass", "series": "AH", "poll_hz": 20}])],
            "http": {"token": TOKEN, "allow_commands": True}}
        with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
            log_in(driver, base, "", TOKEN, "admin")  # (http.token is an admin's)
            driver.find_element("css selector", 'a[href="wizards"]').click()
            button = driver.find_element("css selector", '[data-procedure="mag_calibration"]')
            wait(lambda: button.is_enabled() and driver.find_element(
                "id", "sensor").get_attribute("value") == "compass", "the sensor is listed")
            button.click()
            circling = wait(lambda: when(driver, lambda s: s["step"] == "circle"),
                            "the page asks for the circle")
            assert circling["prompt"].startswith("Turn the sensor slowly through one full")
            sim.call(compass.turn, 0.0, 90.0, time.monotonic()).result(5)  # a turn in 4 s
            part = wait(lambda: when(driver, lambda s: 0 < float(s["coverage"]) < 100),
                        "the coverage grows")
            done = wait(lambda: when(driver, lambda s: s["state"] == "done"),
                        "the calibration is done", timeout=30)
            screenshot(driver, tmp_path, "wizards-mag-done.png")
            assert done["coverage"] == "100" and done["save"] and done["points"] >= 30
            assert done["prompt"] == "done: save now, to keep it"
            assert 0 < float(part["coverage"]) < 100
            driver.find_element("id", "save").click()
            said = wait(lambda: str(shown(driver)["result"]), "save answers")
            assert said == "saved: the sensor is busy for a few seconds"
            assert console_errors(driver) == []
            runs = get_json(f"{base}/api/v1/sensors/compass/procedures")["runs"]
            assert [(r["procedure"], r["state"]) for r in runs] == [("mag_calibration", "done")]
        heard = compass.writes_heard
        assert (heard["clear_mag_calibration"], heard["start_mag_calibration"],
                heard["finish_mag_calibration"], heard["save"]) == (1, 1, 1, 1)


CHECKS_JS = """
return Array.from(document.querySelectorAll('#change-checks li'),
                  (li) => [li.dataset.check, li.dataset.ok === '1', li.textContent]);
"""


def test_the_address_wizard_checks_then_moves_the_sensor_and_the_config(
        tmp_path: Path) -> None:
    """Two sensors on a line: the page's checks say the other's address is taken and the
    baud rate cannot change; a free address is set with a click, and the config file
    follows."""
    boom = make_sensor(WireProtocol.NATIVE, Series.VG, 0, baud=FAST, source=hold(READING))
    arm = make_sensor(WireProtocol.NATIVE, Series.VG, 1, baud=FAST, source=hold(READING))
    with simulated([boom, arm]) as sim:
        cfg = {"gateway_id": "wiz", "buses": [bus("line", sim.path, "native", [
            {"name": "boom", "series": "VG", "address": 0, "poll_hz": 10},
            {"name": "arm", "series": "VG", "address": 1, "poll_hz": 10}])],
            "http": {"token": TOKEN, "allow_commands": True}}
        with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
            log_in(driver, base, "", TOKEN, "admin")
            driver.find_element("css selector", 'a[href="wizards"]').click()
            change = driver.find_element("css selector", '[data-procedure="change_address"]')
            wait(lambda: driver.find_element("id", "sensor").get_attribute("value") == "boom"
                 and driver.execute_script(CHECKS_JS), "the checks are shown")
            field = driver.find_element("id", "new-address")
            field.send_keys("1")
            checks = wait(lambda: [c for c in driver.execute_script(CHECKS_JS)
                                   if c[0] == "address" and "taken" in c[2]], "taken")
            assert checks == [["address", False, "address 1 is taken on bus line by arm"]]
            assert not change.is_enabled()
            baud = [c for c in driver.execute_script(CHECKS_JS) if c[0] == "baud"]
            assert baud[0][1] is False and "other sensors (arm)" in baud[0][2]
            field.clear()
            field.send_keys("9")
            wait(lambda: change.is_enabled(), "a free address may be set")
            change.click()
            done = wait(lambda: when(driver, lambda s: s["state"] == "done"),
                        "the address is changed", timeout=30)
            screenshot(driver, tmp_path, "wizards-address-done.png")
            assert done["result"].startswith("the config follows: saved to ")
            assert console_errors(driver) == []
            assert boom.address == 9
            saved = yaml.safe_load((tmp_path / "gateway.yaml").read_text())
            assert [s["address"] for s in saved["buses"][0]["sensors"]] == [9, 1]
            listed = get_json(f"{base}/api/v1/sensors")
            assert [(s["name"], s["address"]) for s in listed] == [("boom", 9), ("arm", 1)]
