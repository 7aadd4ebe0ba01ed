"""The wizards page (docs/wizards.md, docs/dashboard.md) in a real headless Chromium, with
real clicks, against ``python -m imu_gateway run`` on a simulated AH sensor turned as a
person would turn it: the magnetic calibration reaches "done" with coverage 100 %, and
Save is offered and carried out.  Waits are deadlines on a condition."""

from __future__ import annotations

import time
from collections.abc import Callable
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

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

TOKEN = "wizard-page-token"

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
