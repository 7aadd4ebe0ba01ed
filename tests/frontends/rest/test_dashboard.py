"""The live dashboard at ``GET /`` (docs/dashboard.md, issue 6) in a real headless Chromium.

The gateway runs in a subprocess (``python -m imu_gateway run``) on simulated sensors on
real pseudo-terminals, served from this process; selenium drives Chromium through
Debian's chromedriver.  The dashboard's test hooks: each sensor's card has
``data-sensor``, its horizon canvas ``data-pitch``/``data-roll``/``data-yaw`` (the values
it was last drawn with), value cells ``data-field``; each bus card has ``data-bus``.
What the page shows is compared with the REST API's reading of the same sensor.
Waits are deadlines on a condition.  Screenshots go to ``test-artifacts/``.
"""

from __future__ import annotations

import contextlib
import functools
import json
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest
import yaml
from support import ROOT
from support.harness import free_port, interrupt

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

webdriver = pytest.importorskip("selenium.webdriver")
from selenium.webdriver.chrome.service import Service  # noqa: E402

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"
if not Path(CHROMIUM).exists() or not Path(CHROMEDRIVER).exists():
    pytest.skip("chromium and chromedriver are not installed (scripts/bootstrap)",
                allow_module_level=True)

FAST = 115200
ARTIFACTS = ROOT / "test-artifacts"
T = TypeVar("T")

# Every value the page shows of a sensor, in one round trip.
STATE_JS = """
const card = document.querySelector(`[data-sensor="${arguments[0]}"]`);
if (!card) return null;
const canvas = card.querySelector("canvas.horizon");
const fields = {};
for (const el of card.querySelectorAll("[data-field]")) fields[el.dataset.field] = el.textContent;
return {fields, horizon: canvas.hidden ? null : {...canvas.dataset},
        noAttitude: !card.querySelector(".no-attitude").hidden};
"""


def wait(condition: Callable[[], T | None], what: str, timeout: float = 15.0) -> T:
    """Poll until ``condition()`` is truthy; its value.  A deadline, not a measurement."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        time.sleep(0.05)




def get_json(url: str, token: str | None = None) -> Any:
    request = urllib.request.Request(url)
    if token is not None:
        request.add_header("Authorization", f"Bearer {token}")
    with urllib.request.urlopen(request, timeout=5) as response:
        return json.loads(response.read())


@contextlib.contextmanager
def gateway(tmp_path: Path, cfg: dict[str, Any], token: str | None = None) -> Iterator[str]:
    """``python -m imu_gateway run`` on ``cfg``; its base URL once the API answers."""
    port = free_port()
    cfg = {**cfg, "http": {**cfg.get("http", {}), "listen": f"127.0.0.1:{port}"}}
    path = tmp_path / "gateway.yaml"
    path.write_text(yaml.safe_dump(cfg))
    log_path = tmp_path / "gateway.log"
    with log_path.open("wb") as log:
        process = subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c", str(path)],
                                   stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"

    def up() -> bool:
        if process.poll() is not None:
            raise AssertionError(f"the gateway exited:\n{log_path.read_text()}")
        try:
            get_json(f"{base}/api/v1/health", token)
        except (OSError, urllib.error.URLError):
            return False
        return True

    try:
        wait(up, "the gateway's API answers", timeout=30)
        yield base
    finally:
        interrupt(process)


@contextlib.contextmanager
def chromium(tmp_path: Path) -> Iterator[Any]:
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--disable-quic",
                 "--window-size=1400,1200", f"--user-data-dir={tmp_path / 'chromium'}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))
    try:
        driver.set_script_timeout(10)
        yield driver
    finally:
        driver.quit()


def log_in(driver: Any, base: str, user: str, password: str, role: str) -> None:
    """Open the page and log in with its form (no user name: ``password`` is a token of
    ``http.tokens``), as a person would: typed and clicked; until the page says who."""
    driver.get(base + "/")
    form = driver.find_element("id", "login")
    if not form.is_displayed():  # reads are open: the form is a click away
        wait(lambda: driver.find_element("id", "login-open").is_displayed(), "Log in")
        driver.find_element("id", "login-open").click()
    driver.find_element("id", "login-user").send_keys(user)
    driver.find_element("id", "login-password").send_keys(password)
    form.find_element("css selector", "button[type=submit]").click()
    wait(lambda: driver.execute_script(  # (one call: the page reloads once logged in)
        "const w = document.getElementById('who');"
        "return w && !document.getElementById('logout').hidden ? w.dataset.role : null;")
        == role, f"logged in as {role}")


def console_errors(driver: Any) -> list[dict[str, Any]]:
    """SEVERE console entries since the last call (the browser's log is drained)."""
    return [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]


def shown(driver: Any, sensor: str) -> dict[str, Any] | None:
    value = driver.execute_script(STATE_JS, sensor)
    assert value is None or isinstance(value, dict)
    return value


def angle_gap(a: float, b: float) -> float:
    """|a - b| for headings, across the 0/360 wrap."""
    return abs((a - b + 180.0) % 360.0 - 180.0)


def screenshot(driver: Any, tmp_path: Path, name: str) -> Path:
    path = tmp_path / name
    assert driver.save_screenshot(str(path))
    ARTIFACTS.mkdir(exist_ok=True)
    shutil.copyfile(path, ARTIFACTS / name)
    return path


def bus(name: str, port: str, protocol: str, sensors: list[dict[str, Any]]) -> dict[str, Any]:
    return {"name": name, "port": port, "baudrate": FAST, "protocol": protocol,
            "timeout_ms": 300, "sensors": sensors}


def agrees(driver: Any, reading_url: str, sensor: str, token: str | None = None,
           margin: float = 1.0) -> dict[str, Any] | None:
    """The page's values of ``sensor`` when they lie between two REST readings taken
    just before and just after (``margin`` degrees for motion and the page's lag of a
    frame or a reading), or None."""
    before = get_json(reading_url, token)
    state = shown(driver, sensor)
    after = get_json(reading_url, token)
    if state is None or state["horizon"] is None or "pitch" not in state["fields"]:
        return None
    for axis in ("pitch", "roll", "yaw"):
        value = float(state["fields"][axis])
        b, a = before["angles"][axis], after["angles"][axis]
        if angle_gap(value, b) + angle_gap(value, a) > angle_gap(b, a) + 2 * margin:
            return None
    if not before["seq"] - 5 <= int(state["fields"]["seq"]) <= after["seq"]:
        return None
    return state


def moves(driver: Any, sensor: str) -> dict[str, Any]:
    """The sensor's horizon once it has been drawn with two different pitches."""

    def drawn() -> dict[str, Any] | None:
        s = shown(driver, sensor)
        return s if s and s["horizon"] and "pitch" in s["horizon"] else None

    first = wait(drawn, f"{sensor}'s horizon is drawn")
    pitch, text = float(first["horizon"]["pitch"]), first["fields"]["pitch"]

    def changed() -> dict[str, Any] | None:
        s = shown(driver, sensor)
        return s if s and abs(float(s["horizon"]["pitch"]) - pitch) > 0.01 and \
            s["fields"]["pitch"] != text else None

    return wait(changed, f"{sensor}'s pitch changes")


def test_the_dashboard_follows_the_sensors_the_buses_and_the_stream(tmp_path: Path) -> None:
    faults = Faults()
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST, source=Motion.from_seed(7),
                       faults=faults)
    arm = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=FAST, source=Motion.from_seed(11))
    wrist = make_sensor(WireProtocol.MODBUS, Series.IMU, 2, baud=FAST, source=Motion.from_seed(5))
    with simulated([boom]) as line_a, simulated([arm, wrist]) as line_b:
        cfg = {"gateway_id": "dash", "buses": [
            bus("a", line_a.path, "native", [{"name": "boom", "series": "AH", "poll_hz": 20}]),
            bus("b", line_b.path, "modbus", [
                {"name": "arm", "series": "VG", "address": 1, "poll_hz": 10},
                {"name": "wrist", "series": "IMU", "address": 2, "poll_hz": 10}])]}
        with gateway(tmp_path, cfg) as base, chromium(tmp_path) as driver:
            driver.get(base + "/")
            for name in ("boom", "arm", "wrist"):
                wait(functools.partial(shown, driver, name), f"{name}'s card")

            # The horizon and the values move with the sensor, and agree with REST.
            moves(driver, "boom")
            state = wait(lambda: agrees(driver, f"{base}/api/v1/sensors/boom/reading", "boom"),
                         "boom's shown angles agree with its REST reading")
            horizon, fields = state["horizon"], state["fields"]
            for axis in ("pitch", "roll", "yaw"):  # drawn as shown, to the 2 decimals
                assert abs(float(horizon[axis]) - float(fields[axis])) <= 0.005 + 1e-9, axis
            for field in ("accel_x", "gyro_y", "mag_z", "q0"):  # AH: every group
                assert field in fields and fields[field] not in ("", "–"), field
            assert fields["status"] == "ok" and int(fields["seq"]) > 0
            assert fields["age"].endswith(("ms", "s"))

            arm_state = moves(driver, "arm")  # VG: angles, accel, gyro, quaternion; no mag
            assert "q3" in arm_state["fields"] and "mag_x" not in arm_state["fields"]

            def wrist_values() -> dict[str, Any] | None:
                s = shown(driver, "wrist")
                return s if s and "accel_z" in s["fields"] else None

            wrist_state = wait(wrist_values, "wrist's values")
            assert wrist_state["noAttitude"] and wrist_state["horizon"] is None
            assert "pitch" not in wrist_state["fields"]  # IMU: no angles

            # Each bus's health, from GET /api/v1/buses.
            for name, protocol, sensors in (("a", "native", "boom"), ("b", "modbus", "arm")):
                text = wait(functools.partial(
                    driver.execute_script,
                    "const b = document.querySelector(`[data-bus=\"${arguments[0]}\"]`);"
                    "return b && b.textContent.includes('port open') && b.innerText;", name),
                    f"bus {name}'s health")
                assert str(FAST) in text and protocol in text and sensors in text, text
                assert "transactions/s" in text and "utilisation" in text, text

            assert driver.find_element("id", "banner").is_displayed() is False
            assert console_errors(driver) == []
            screenshot(driver, tmp_path, "dashboard.png")

            # A phone: one column, nothing wider than the screen.
            driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", {
                "width": 390, "height": 844, "deviceScaleFactor": 2, "mobile": True})
            wait(lambda: driver.execute_script("return window.innerWidth") == 390,
                 "the phone viewport")
            time.sleep(0.3)  # a few frames, so the canvases follow the new size
            assert driver.execute_script(
                "return document.documentElement.scrollWidth <= window.innerWidth + 1")
            screenshot(driver, tmp_path, "dashboard-phone.png")
            driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})

            # A sensor that stops answering is shown offline.
            faults.stalled = True
            wait(lambda: (s := shown(driver, "boom")) and s["fields"]["status"] == "offline",
                 "boom shown offline")
            assert get_json(f"{base}/api/v1/sensors/boom/reading")["status"] == "offline"
            assert console_errors(driver) == []
            screenshot(driver, tmp_path, "dashboard-offline.png")


def test_the_stream_going_down_shows_a_banner(tmp_path: Path) -> None:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST, source=Motion.from_seed(7))
    with simulated([boom]) as line, chromium(tmp_path) as driver:
        cfg = {"gateway_id": "dash", "buses": [
            bus("a", line.path, "native", [{"name": "boom", "series": "AH", "poll_hz": 20}])]}
        with gateway(tmp_path, cfg) as base:
            driver.get(base + "/")
            moves(driver, "boom")
            assert not driver.find_element("id", "banner").is_displayed()
        banner = driver.find_element("id", "banner")
        wait(banner.is_displayed, "the disconnected banner")
        assert "disconnected" in banner.text


def test_with_a_read_token_the_dashboard_logs_in_and_streams(tmp_path: Path) -> None:
    """Reads need a credential: the page shows its login form; a token in the address
    is taken out of it and not used; logged in with the form (the token as password),
    the page streams (by fetch, with the header: no token in any URL)."""
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST, source=Motion.from_seed(7))
    with simulated([boom]) as line:
        cfg = {"gateway_id": "dash", "http": {"token": "s3cret", "read_token_required": True},
               "buses": [bus("a", line.path, "native",
                             [{"name": "boom", "series": "AH", "poll_hz": 20}])]}
        with gateway(tmp_path, cfg, token="s3cret") as base, chromium(tmp_path) as driver:
            driver.get(base + "/?token=s3cret")  # the old way: no longer a credential
            form = driver.find_element("id", "login")
            wait(form.is_displayed, "the login form")
            assert "token" not in driver.current_url
            assert "not used" in driver.find_element("id", "login-result").text
            log_in(driver, base, "", "s3cret", "admin")
            assert {e["message"].split(" - ")[0] for e in console_errors(driver)} <= {
                f"{base}/api/v1/me"}  # its 401 before the login was expected
            moves(driver, "boom")  # (readings come by the stream only)
            wait(lambda: agrees(driver, f"{base}/api/v1/sensors/boom/reading", "boom",
                                "s3cret"), "boom's shown angles agree with REST")
            assert driver.find_element("id", "mode").text.endswith("live")
            assert not driver.find_element("id", "banner").is_displayed()
            urls = driver.execute_script(
                "return performance.getEntriesByType('resource').map((e) => e.name)")
            assert any("/api/v1/sensors" in u for u in urls)  # (the stream is not done)
            assert not [u for u in urls if "s3cret" in u]
            assert console_errors(driver) == []


CARD_JS = """
const card = document.querySelector(`[data-sensor="${arguments[0]}"]`);
if (!card) return null;
const trends = {};
for (const c of card.querySelectorAll("canvas.trend"))
  trends[c.dataset.group] = {points: Number(c.dataset.points || 0),
                             seconds: Number(c.dataset.seconds || 0),
                             legend: c.dataset.legend, axis: c.dataset.axis};
const filter = getComputedStyle(card.querySelector("canvas.horizon")).filter;
return {classes: [...card.classList], reason: card.querySelector(".reason").textContent,
        filter, trends, rate: card.querySelector('[data-field="rate"]').textContent,
        errors: card.querySelector('[data-field="errors"]').textContent,
        buttons: [...card.querySelectorAll(".commands button")].map((b) => b.dataset.command),
        result: card.querySelector(".command-result").textContent,
        units: [...card.querySelectorAll(".gname small")].map((u) => u.textContent)};
"""


def card(driver: Any, sensor: str) -> dict[str, Any] | None:
    value = driver.execute_script(CARD_JS, sensor)
    assert value is None or isinstance(value, dict)
    return value


def card_when(driver: Any, sensor: str, ok: Callable[[dict[str, Any]], bool],
              what: str) -> dict[str, Any]:
    def check() -> dict[str, Any] | None:
        c = card(driver, sensor)
        return c if c is not None and ok(c) else None

    return wait(check, what)


def test_the_dashboard_is_honest_keeps_trends_and_runs_commands(tmp_path: Path) -> None:
    """Stale, offline and waiting cards look unlike a fresh one and say why; the trend
    starts with the gateway's history; a command button reaches the sensor."""
    token = "dash-token"
    boom_faults, mute_faults = Faults(), Faults(stalled=True)
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST, source=Motion.from_seed(5),
                       faults=boom_faults)
    mute = make_sensor(WireProtocol.NATIVE, Series.VG, 1, baud=FAST, faults=mute_faults)
    with simulated([boom, mute]) as line:
        cfg = {"gateway_id": "dash", "buses": [bus("a", line.path, "native", [
            {"name": "boom", "series": "AH", "poll_hz": 20, "stale_after_ms": 1500},
            {"name": "mute", "series": "VG", "address": 1, "poll_hz": 5}])],
            "http": {"token": token, "allow_commands": True}}
        with gateway(tmp_path, cfg, token) as base, chromium(tmp_path) as driver:
            # Some seconds of history before the page opens: the trend starts with them.
            wait(lambda: get_json(f"{base}/api/v1/sensors/boom", token)["seq"] > 60,
                 "three seconds of readings", timeout=30)
            past = get_json(f"{base}/api/v1/sensors/boom/history", token)["t"]
            log_in(driver, base, "", token, "admin")
            # every second the gateway had before the page opened is in the trend
            fresh = card_when(driver, "boom", lambda c: "is-ok" in c["classes"] and
                              c["trends"].get("angles", {}).get("points", 0) >= len(past)
                              and c["trends"]["angles"]["seconds"] >= past[-1] - past[0],
                              "boom ok, with its past")
            assert fresh["filter"] == "none" and not fresh["reason"]
            # each chart has a legend of its fields and an axis of its own; a direction
            # (0-360: yaw, tilt_direction) is drawn apart, not on its group's axis
            assert fresh["trends"]["angles"]["legend"] == "pitch,roll"
            assert fresh["trends"]["yaw"]["legend"] == "yaw"
            assert fresh["trends"]["accel"]["legend"] == "x,y,z"
            assert fresh["trends"]["tilt"]["legend"] == "tilt"
            assert fresh["trends"]["tilt_direction"]["legend"] == "tilt_direction"
            for chart in fresh["trends"].values():
                low, high = map(float, chart["axis"].split())
                assert low < high, fresh["trends"]
            assert "gauss" in fresh["units"] and "G" not in fresh["units"]
            assert "/" in fresh["rate"] and "/min" in fresh["errors"]
            # the sensor that never answers: offline, and it says so (after its tries)
            silent = card_when(driver, "mute", lambda c: "is-offline" in c["classes"],
                               "mute offline")
            assert "never answered" in silent["reason"] and silent["filter"] != "none"
            # a command button, from the catalogue, reaching the sensor
            assert "calibrate_gyro" in fresh["buttons"] and "set_zero_type" not in fresh["buttons"]
            before = boom.writes_heard["calibrate_gyro"]
            driver.find_element("css selector",
                                '[data-sensor="boom"] [data-command="calibrate_gyro"]').click()
            done = card_when(driver, "boom", lambda c: "ok" in c["result"],
                             "the command's result")
            assert done["result"].startswith("calibrate_gyro: ok")
            assert boom.writes_heard["calibrate_gyro"] == before + 1
            screenshot(driver, tmp_path, "dashboard-ok-offline-command.png")
            # stale: greyed, with the time of its last reading
            boom_faults.stalled = True
            stale = card_when(driver, "boom", lambda c: "is-stale" in c["classes"] or
                              "is-offline" in c["classes"], "boom stale")
            assert stale["filter"] != "none" and "last reading" in stale["reason"]
            screenshot(driver, tmp_path, "dashboard-stale.png")
            assert not console_errors(driver)
