"""A real Home Assistant Core against the gateway and a real mosquitto.

Home Assistant 2024.3.3 (the last that runs on Python 3.11) lives in a venv of its own,
outside the checkout (``~/.cache/imu-gateway/``), made by this test the first time
(several minutes; it is skipped, saying why, only when it cannot be installed).  Home
Assistant is started by the test, its MQTT integration set up through its own config
flow, and everything is checked through its REST API:

* the entities, their units and the device tree (each sensor via the gateway);
* the attributes (status, ts, seq);
* unavailable when the sensor is stalled, when the gateway stops, and when it is
  killed (its last will);
* a button press reaching the simulated sensor;
* an alarm on the tilt (docs/alarms.md): its ``problem`` binary sensor turning on when
  the simulated sensor leans past the limit for the on-delay, staying on through the
  hysteresis, off below it, and the acknowledge button acknowledging it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml
from support.broker import Mosquitto
from support.harness import free_port

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, SimulatorThread, make_sensor
from imu_gateway.simulator.motion import Motion

HA_VERSION = "2024.3.3"
# josepy 2 dropped what Home Assistant 2024.3's cloud integration imports (acme)
HA_PINS = [f"homeassistant=={HA_VERSION}", "josepy<2", "paho-mqtt==1.6.1"]
CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "imu-gateway"
GID = "plant"
ON_DELAY = 1.0
BOOM_LEAN = {"name": "boom_lean", "field": "tilt", "above": 5.0, "hysteresis": 0.5,
             "on_delay_s": ON_DELAY}
PROBLEM, ACKNOWLEDGE = "binary_sensor.plant_boom_boom_lean_alarm", \
    "button.plant_boom_acknowledge_boom_lean"

pytestmark = pytest.mark.timeout(1200)


def _ha_venv() -> Path:
    """Home Assistant's own venv (made once); skips when it cannot be installed."""
    venv = CACHE / f"homeassistant-{HA_VERSION}"
    hass = venv / "bin" / "hass"
    if hass.exists():
        return hass
    shutil.rmtree(venv, ignore_errors=True)
    venv.parent.mkdir(parents=True, exist_ok=True)
    done = subprocess.run([sys.executable, "-m", "venv", str(venv)], capture_output=True,
                          text=True)
    if done.returncode == 0:
        done = subprocess.run([str(venv / "bin" / "pip"), "install", "--quiet",
                               "--disable-pip-version-check", *HA_PINS],
                              capture_output=True, text=True, timeout=1200)
    if done.returncode != 0:
        shutil.rmtree(venv, ignore_errors=True)
        pytest.skip(f"Home Assistant {HA_VERSION} cannot be installed here: "
                    f"{done.stderr.strip()[-300:]}")
    return hass


class HomeAssistant:
    """A running Home Assistant, logged in through its REST API."""

    def __init__(self, hass: Path, config: Path, port: int) -> None:
        self.base = f"http://127.0.0.1:{port}"
        (config / "configuration.yaml").write_text(yaml.safe_dump({
            "homeassistant": {"name": "test", "unit_system": "metric", "time_zone": "UTC",
                              "latitude": 0, "longitude": 0, "elevation": 0},
            "http": {"server_host": "127.0.0.1", "server_port": port}, "api": None}))
        subprocess.run([str(hass), "--script", "auth", "-c", str(config), "add", "tester",
                        "secret"], check=True, capture_output=True, timeout=120)
        self.log = (config / "hass.out").open("w")
        # without --skip-pip: the first start installs what its own integrations need
        self.process = subprocess.Popen([str(hass), "-c", str(config)], stdout=self.log,
                                        stderr=subprocess.STDOUT)
        self.http = httpx.Client(base_url=self.base, timeout=30)
        self._until(lambda: self._answers(), 600, "Home Assistant's API")
        self.http.headers["Authorization"] = f"Bearer {self._token()}"

    def _answers(self) -> bool:
        try:
            return self.http.get("/api/").status_code == 401
        except httpx.HTTPError:
            return False

    def _token(self) -> str:
        client = self.base + "/"
        flow = self.http.post("/auth/login_flow", json={
            "client_id": client, "handler": ["homeassistant", None],
            "redirect_uri": client}).json()
        code = self.http.post(f"/auth/login_flow/{flow['flow_id']}", json={
            "client_id": client, "username": "tester", "password": "secret"}).json()
        token = self.http.post("/auth/token", data={
            "grant_type": "authorization_code", "code": code["result"],
            "client_id": client}).json()
        return str(token["access_token"])

    def add_mqtt(self, port: int) -> None:
        """Its MQTT integration, set up as a user would, through the config flow."""
        flow = self.http.post("/api/config/config_entries/flow",
                              json={"handler": "mqtt", "show_advanced_options": False}).json()
        done = self.http.post(f"/api/config/config_entries/flow/{flow['flow_id']}",
                              json={"broker": "127.0.0.1", "port": port}).json()
        assert done["type"] == "create_entry", done

    def state(self, entity: str) -> dict[str, Any] | None:
        got = self.http.get(f"/api/states/{entity}")
        return got.json() if got.status_code == 200 else None

    def template(self, text: str) -> str:
        return self.http.post("/api/template", json={"template": text}).text

    def wait_state(self, entity: str, check: Any, what: str, timeout: float = 60) -> None:
        self._until(lambda: (s := self.state(entity)) is not None and check(s["state"]),
                    timeout, f"{entity} {what}")

    @staticmethod
    def _until(condition: Any, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
            time.sleep(0.2)

    def close(self) -> None:
        self.process.terminate()
        self.process.wait(60)
        self.http.close()
        self.log.close()


@pytest.fixture(scope="module")
def hass_bin() -> Path:
    return _ha_venv()


@pytest.fixture
def home_assistant(hass_bin: Path, tmp_path: Path) -> Iterator[HomeAssistant]:
    config = tmp_path / "ha"
    config.mkdir()
    ha = HomeAssistant(hass_bin, config, free_port())
    try:
        yield ha
    finally:
        ha.close()


def _gateway(line: str, broker: Mosquitto, path: Path) -> subprocess.Popen[bytes]:
    path.write_text(yaml.safe_dump({
        "gateway_id": GID,
        "buses": [{"name": "line-a", "port": line, "baudrate": 115200, "protocol": "native",
                   "timeout_ms": 300,
                   "sensors": [{"name": "boom", "series": "AH", "poll_hz": 5,
                                "stale_after_ms": 1500, "alarms": [BOOM_LEAN]}]}],
        "mqtt": {"url": broker.url, "homeassistant_discovery": True, "allow_commands": True,
                 "homeassistant_min_interval_ms": 500}}))
    return subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c", str(path)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _number(state: str) -> bool:
    try:
        float(state)
    except ValueError:
        return False
    return True


def test_home_assistant_sees_the_gateway_as_its_users_expect(
        home_assistant: HomeAssistant, tmp_path: Path) -> None:
    ha = home_assistant
    ah: SimSensor = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200,
                                source=Motion.from_seed(7))
    with Mosquitto(tmp_path) as broker, SimulatorThread([ah]) as line:
        line.call(ah.lean, 1.0, 0.0).result(5)  # level enough: the alarm is normal
        ha.add_mqtt(broker.port)
        gateway = _gateway(line.path, broker, tmp_path / "gateway.yaml")
        try:
            _entities_units_and_devices(ha)
            _stale_is_unavailable(ha, ah)
            _button_reaches_the_sensor(ha, ah)
            _the_alarm_follows_the_lean(ha, ah, line)
            gateway.send_signal(signal.SIGTERM)  # a clean stop: "offline"
            assert gateway.wait(30) == 0
            ha.wait_state("sensor.plant_boom_pitch", lambda s: s == "unavailable",
                          "unavailable after the gateway stopped")
            gateway = _gateway(line.path, broker, tmp_path / "gateway.yaml")
            ha.wait_state("sensor.plant_boom_pitch", _number, "back")
            gateway.kill()  # no goodbye: the broker's last will
            gateway.wait(30)
            ha.wait_state("sensor.plant_boom_pitch", lambda s: s == "unavailable",
                          "unavailable after the gateway was killed")
        finally:
            if gateway.poll() is None:
                gateway.kill()
                gateway.wait(30)


def _entities_units_and_devices(ha: HomeAssistant) -> None:
    ha.wait_state("sensor.plant_boom_pitch", _number, "a number")
    pitch = ha.state("sensor.plant_boom_pitch")
    assert pitch is not None
    attributes = pitch["attributes"]
    assert attributes["unit_of_measurement"] == "°"
    assert attributes["status"] == "ok" and attributes["seq"] >= 1 and attributes["ts"]
    assert attributes["friendly_name"] == "plant boom pitch"
    gyro = ha.state("sensor.plant_boom_gyro_x")
    assert gyro is not None and gyro["attributes"]["unit_of_measurement"] == "°/s"
    assert ha.state("sensor.plant_boom_q0") is None  # disabled by default
    link = "binary_sensor.imu_gateway_plant_connectivity"
    ha.wait_state(link, lambda s: s == "on", "connected")
    # the device tree: the sensor's device is via the gateway's
    via = ha.template("{{ device_attr(device_id('sensor.plant_boom_pitch'), "
                      "'via_device_id') }}")
    assert via == ha.template(f"{{{{ device_id('{link}') }}}}") and via
    assert ha.template("{{ device_attr(device_id('sensor.plant_boom_pitch'), 'model') }}") \
        == "AH series"


def _stale_is_unavailable(ha: HomeAssistant, ah: SimSensor) -> None:
    ah.faults.stalled = True
    ha.wait_state("sensor.plant_boom_pitch", lambda s: s == "unavailable",
                  "unavailable once stale")
    ah.faults.stalled = False
    ha.wait_state("sensor.plant_boom_pitch", _number, "back once answering")


def _button_reaches_the_sensor(ha: HomeAssistant, ah: SimSensor) -> None:
    before = ah.writes_heard["calibrate_gyro"]
    ha.wait_state("button.plant_boom_calibrate_gyro", lambda s: s != "unavailable",
                  "available")
    pressed = ha.http.post("/api/services/button/press",
                           json={"entity_id": "button.plant_boom_calibrate_gyro"})
    assert pressed.status_code == 200, pressed.text
    ha._until(lambda: ah.writes_heard["calibrate_gyro"] > before, 30,
              "the sensor heard the calibration")


def _attribute(ha: HomeAssistant, entity: str, name: str) -> Any:
    state = ha.state(entity)
    return None if state is None else state["attributes"].get(name)


def _the_alarm_follows_the_lean(ha: HomeAssistant, ah: SimSensor,
                                line: SimulatorThread) -> None:
    ha.wait_state(PROBLEM, lambda s: s == "off", "off while the boom is level")
    problem = ha.state(PROBLEM)
    assert problem is not None and problem["attributes"]["device_class"] == "problem"
    assert problem["attributes"]["alarm_state"] == "normal"
    leaned_at = time.time()
    line.call(ah.lean, 7.5, 0.0).result(5)
    ha.wait_state(PROBLEM, lambda s: s == "on", "on once leaning past 5 degrees")
    assert _attribute(ha, PROBLEM, "alarm_state") == "active_unacked"
    assert (_attribute(ha, PROBLEM, "value"), _attribute(ha, PROBLEM, "limit")) == (7.5, 5.0)
    since = datetime.fromisoformat(_attribute(ha, PROBLEM, "since")).timestamp()
    assert since >= leaned_at + ON_DELAY - 0.002  # not before the on-delay

    ha.wait_state(ACKNOWLEDGE, lambda s: s != "unavailable", "available")
    pressed = ha.http.post("/api/services/button/press", json={"entity_id": ACKNOWLEDGE})
    assert pressed.status_code == 200, pressed.text
    ha._until(lambda: _attribute(ha, PROBLEM, "alarm_state") == "active_acked", 30,
              "the alarm acknowledged")
    assert ha.state(PROBLEM)["state"] == "on"  # type: ignore[index]

    # back under the limit, not through the hysteresis: still on
    line.call(ah.lean, 4.7, 0.0).result(5)
    ha.wait_state("sensor.plant_boom_tilt", lambda s: _number(s) and float(s) == 4.7,
                  "the tilt at 4.7")
    assert ha.state(PROBLEM)["state"] == "on"  # type: ignore[index]
    line.call(ah.lean, 4.0, 0.0).result(5)
    ha.wait_state(PROBLEM, lambda s: s == "off", "off through the hysteresis")
    assert _attribute(ha, PROBLEM, "alarm_state") == "normal"
