"""The MQTT front end's pure rules (``frontends.mqtt_topics``): topics, Home Assistant
discovery configs, the deadband and the minimum interval.  On values alone."""

from __future__ import annotations

from imu_gateway.config import SensorConfig
from imu_gateway.frontends.mqtt_topics import (
    Topics,
    discovery_configs,
    send_delay,
    within_deadband,
)
from imu_gateway.model import Series

TOPICS = Topics("imu", "plant.1", "homeassistant")


def test_topics_and_object_ids() -> None:
    assert TOPICS.status == "imu/plant.1/status"
    assert TOPICS.sensor("boom", "state") == "imu/plant.1/boom/state"
    # Home Assistant's object ids allow no dots
    assert TOPICS.discovery("boom", "pitch") == "homeassistant/sensor/plant_1_boom_pitch/config"


def test_one_entity_per_measured_field_with_its_unit() -> None:
    configs = discovery_configs(TOPICS, {
        "boom": SensorConfig(name="boom", series=Series.AH, address=1),
        "arm": SensorConfig(name="arm", series=Series.IMU, address=2)})
    ah = [c for c in configs.values() if c["state_topic"] == "imu/plant.1/boom/state"]
    imu = [c for c in configs.values() if c["state_topic"] == "imu/plant.1/arm/state"]
    assert len(ah) == 16 and len(imu) == 6  # an IMU measures no angles, field or quaternion
    pitch = configs["homeassistant/sensor/plant_1_boom_pitch/config"]
    assert pitch["unit_of_measurement"] == "°"
    assert pitch["value_template"] == "{{ value_json.angles.pitch }}"
    assert "unit_of_measurement" not in configs["homeassistant/sensor/plant_1_boom_q0/config"]
    assert {c["unique_id"] for c in configs.values()} == \
        {t.split("/")[2] for t in configs}  # unique ids are the object ids


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
