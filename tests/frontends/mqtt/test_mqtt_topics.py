"""The MQTT front end's pure rules (``frontends/mqtt/topics.py``): topics, Home Assistant
discovery configs, the deadband and the minimum interval.  On values alone."""

from __future__ import annotations

from typing import Any

from imu_gateway.config import SensorConfig
from imu_gateway.frontends.mqtt.discovery import Setup, discovery_configs
from imu_gateway.frontends.mqtt.topics import Topics, send_delay, within_deadband
from imu_gateway.model import Series, WireProtocol

TOPICS = Topics("imu", "plant.1", "homeassistant")


def test_topics_and_object_ids() -> None:
    assert TOPICS.status == "imu/plant.1/status"
    assert TOPICS.sensor("boom", "state") == "imu/plant.1/boom/state"
    # Home Assistant's object ids allow no dots
    assert TOPICS.discovery("boom", "pitch") == "homeassistant/sensor/plant_1_boom_pitch/config"


def _setup(commands: bool = False, gateway_id: str = "plant.1") -> Setup:
    return Setup(Topics("imu", gateway_id, "homeassistant"), {
        "boom": (SensorConfig(name="boom", series=Series.AH, address=1), WireProtocol.NATIVE),
        "arm": (SensorConfig(name="arm", series=Series.IMU, address=2), WireProtocol.NATIVE),
        "mast": (SensorConfig(name="mast", series=Series.AH, address=1), WireProtocol.MODBUS),
    }, ("line-a",), commands, "http://box:8080/")


def _sensors(configs: dict[str, Any], sensor: str) -> list[dict[str, Any]]:
    return [c for c in configs.values() if c.get("state_topic") == f"imu/plant.1/{sensor}/ha"]


def test_one_entity_per_measured_field_with_its_unit_and_precision() -> None:
    configs = discovery_configs(_setup())
    ah, imu = _sensors(configs, "boom"), _sensors(configs, "arm")
    # an IMU measures no angles, field or quaternion, so it has no tilt; both have the
    # derived values of what they measure
    assert len(ah) == 16 + 3 and len(imu) == 6 + 1
    tilt = configs["homeassistant/sensor/plant_1_boom_tilt_direction/config"]
    assert tilt["unit_of_measurement"] == "°" and tilt["suggested_display_precision"] == 2
    assert tilt["value_template"] == "{{ value_json.tilt.tilt_direction }}"
    shake = configs["homeassistant/sensor/plant_1_arm_vibration/config"]
    assert shake["unit_of_measurement"] == "g" and shake["suggested_display_precision"] == 4
    assert shake["value_template"] == "{{ value_json.vibration.vibration }}"
    pitch = configs["homeassistant/sensor/plant_1_boom_pitch/config"]
    assert pitch["unit_of_measurement"] == "°" and pitch["suggested_display_precision"] == 2
    assert pitch["value_template"] == "{{ value_json.angles.pitch }}"
    q0 = configs["homeassistant/sensor/plant_1_boom_q0/config"]
    assert "unit_of_measurement" not in q0 and q0["enabled_by_default"] is False
    assert configs["homeassistant/sensor/plant_1_boom_mag_x/config"][
        "suggested_display_precision"] == 5
    assert {c["unique_id"] for c in configs.values()} == \
        {t.split("/")[2] for t in configs}  # unique ids are the object ids


def test_a_stale_reading_is_unavailable_and_its_status_an_attribute() -> None:
    pitch = discovery_configs(_setup())["homeassistant/sensor/plant_1_boom_pitch/config"]
    assert pitch["availability_mode"] == "all"
    topics = [a["topic"] for a in pitch["availability"]]
    assert topics == ["imu/plant.1/status", "imu/plant.1/boom/availability",
                      "imu/plant.1/boom/ha"]
    assert "value_json.status == 'ok'" in pitch["availability"][2]["value_template"]
    assert pitch["json_attributes_topic"] == "imu/plant.1/boom/ha"
    for key in ("status", "ts", "seq"):
        assert f"value_json.{key}" in pitch["json_attributes_template"]


def test_the_gateway_is_a_device_and_each_sensor_is_via_it() -> None:
    configs = discovery_configs(_setup())
    link = configs["homeassistant/binary_sensor/plant_1_connectivity/config"]
    assert link["device_class"] == "connectivity" and link["entity_category"] == "diagnostic"
    assert link["state_topic"] == "imu/plant.1/status"
    gateway = link["device"]
    assert gateway["configuration_url"] == "http://box:8080/"
    for config in configs.values():
        device = config["device"]
        if device is not gateway:
            assert device["via_device"] == gateway["identifiers"][0]
    diagnostics = [c for c in configs.values() if c.get("entity_category") == "diagnostic"]
    assert {c["name"] for c in diagnostics} >= {"line-a utilisation", "readings per second",
                                               "latency", "errors", "connectivity"}


def test_two_gateways_name_their_sensors_apart() -> None:
    one = discovery_configs(_setup(gateway_id="north"))
    two = discovery_configs(_setup(gateway_id="south"))
    names = {c["device"]["name"] for c in one.values()}
    assert not names & {c["device"]["name"] for c in two.values()}
    assert not set(one) & set(two)


def test_commands_are_entities_for_the_series_and_protocol_that_have_them() -> None:
    assert not [t for t in discovery_configs(_setup()) if "/button/" in t]
    configs = discovery_configs(_setup(commands=True))
    kinds = {t.split("/")[1] + ":" + t.split("/")[2] for t in configs
             if t.split("/")[1] in ("button", "select", "number")}
    assert {"button:plant_1_boom_save", "button:plant_1_boom_calibrate_gyro",
            "select:plant_1_boom_set_zero_type", "number:plant_1_boom_set_declination",
            "select:plant_1_boom_mag_calibration"} <= kinds
    assert "button:plant_1_arm_clear_heading" not in kinds  # MINS only
    assert "number:plant_1_mast_set_declination" not in kinds  # no Modbus register
    zero = configs["homeassistant/select/plant_1_boom_set_zero_type/config"]
    assert zero["options"] == ["absolute", "relative"]
    assert zero["command_topic"] == "imu/plant.1/boom/cmd/set_zero_type"
    assert zero["command_template"] == '{"type": {{ value | tojson }}}'
    assert zero["state_topic"] == "imu/plant.1/boom/settings"
    declination = configs["homeassistant/number/plant_1_boom_set_declination/config"]
    assert (declination["min"], declination["max"], declination["step"]) == (-99.9, 99.9, 0.1)


def test_a_reading_is_held_back_only_when_every_banded_field_stayed_within_its_band() -> None:
    bands = {"pitch": 0.5, "roll": 0.5}
    sent = {"pitch": 10.0, "roll": 0.0, "yaw": 3.0}
    assert within_deadband({"pitch": 10.4, "roll": -0.3, "yaw": 90.0}, sent, bands)
    assert not within_deadband({"pitch": 10.6, "roll": 0.0, "yaw": 3.0}, sent, bands)
    assert not within_deadband({"pitch": 10.0}, None, bands)  # nothing sent yet
    assert not within_deadband({"accel_x": 1.0}, sent, bands)  # no banded field in it
    assert not within_deadband({"pitch": 10.0}, sent, {})  # no deadbands at all


def test_the_minimum_interval_delays_and_never_goes_negative() -> None:
    assert abs(send_delay(sent_at=10.0, min_interval_s=0.5, now=10.2) - 0.3) < 1e-9
    assert send_delay(10.0, 0.5, 11.0) == 0.0
    assert send_delay(float("-inf"), 0.5, 0.0) == 0.0
