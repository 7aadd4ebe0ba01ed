"""The config file (docs/configuration.md) and ``imu-gateway check-config``.

Schema rules are checked through ``load_config_text``/``load_config``; a few cases run
the real command as a subprocess.  Every bad config must come back as problems of the
form ``<yaml path>: <message>``, all of them at once, and never as a traceback.
"""

from __future__ import annotations

import copy
import ipaddress
import re
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from support import ROOT

from imu_gateway.config import (
    BusConfig,
    GatewayConfig,
    HttpConfig,
    ListenAddress,
    ModbusConfig,
    MqttConfig,
    SensorConfig,
    config_from_dict,
    load_config,
    load_config_text,
)
from imu_gateway.errors import ConfigError
from imu_gateway.model import Series, WireProtocol
from imu_gateway.passwords import hash_password, verify

CONFIGS = ROOT / "tests" / "configs"
SPEC_EXAMPLE = CONFIGS / "spec_example.yaml"

NATIVE_BUS: dict[str, Any] = {
    "name": "line-a", "port": "/dev/ttyUSB0", "baudrate": 9600, "protocol": "native",
    "sensors": [{"name": "boom", "series": "AH"}],
}
MODBUS_BUS: dict[str, Any] = {
    "name": "line-b", "port": "socket://10.0.0.5:4001", "baudrate": 19200,
    "protocol": "modbus",
    "sensors": [{"name": "arm", "series": "VG"}, {"name": "base", "series": "MINS", "address": 2}],
}
#: A password's hash, as ``imu-gateway hash-password`` makes one.
A_HASH = hash_password("correct horse")


def base(**top: Any) -> dict[str, Any]:
    """A valid two-bus config; keyword arguments replace top-level keys."""
    data: dict[str, Any] = {
        "gateway_id": "lab-1", "buses": [copy.deepcopy(NATIVE_BUS), copy.deepcopy(MODBUS_BUS)],
    }
    data.update(top)
    return data


def problems_of(data: Any, env: dict[str, str] | None = None) -> list[str]:
    text = data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False)
    with pytest.raises(ConfigError) as caught:
        load_config_text(text, "test.yaml", env=env or {})
    assert caught.value.problems, "a ConfigError always lists its problems"
    for problem in caught.value.problems:
        assert "\n" not in problem and "Traceback" not in problem
    return caught.value.problems


def only_problem(data: Any, env: dict[str, str] | None = None) -> str:
    problems = problems_of(data, env)
    assert len(problems) == 1, problems
    return problems[0]


def with_sensor(bus: int, sensor: int, **fields: Any) -> dict[str, Any]:
    data = base()
    data["buses"][bus]["sensors"][sensor].update(fields)
    return data


def with_bus(bus: int, **fields: Any) -> dict[str, Any]:
    data = base()
    data["buses"][bus].update(fields)
    return data


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "imu_gateway", *args], capture_output=True,
                          text=True, timeout=60, check=False)


# ----------------------------------------------------------------- valid configs


def test_spec_example_verbatim_loads() -> None:
    config = load_config(SPEC_EXAMPLE)
    assert config.gateway_id == "lab-1"
    (bus,) = config.buses
    assert (bus.name, bus.port, bus.baudrate, bus.protocol) == (
        "line-a", "/dev/ttyUSB0", 9600, WireProtocol.NATIVE)
    assert (bus.timeout_ms, bus.retries, bus.rs485) == (100, 1, False)
    (sensor,) = bus.sensors
    assert sensor == SensorConfig(name="boom", series=Series.AH, address=0, unit_id=1,
                                  poll_hz=10, stream_hz=0, stale_after_ms=1000,
                                  raw_unit_id=None)
    assert config.modbus is not None and config.mqtt is not None and config.http is not None
    assert config.modbus.listen == ListenAddress("0.0.0.0", 502)
    assert config.modbus.allow_from == [ipaddress.ip_network("0.0.0.0/0")]
    assert config.modbus.allow_writes is False
    assert (str(config.mqtt.brokers[0]), config.mqtt.tls) == ("localhost:1883", False)
    assert config.mqtt.retain is True and config.mqtt.protocol == "3.1.1"
    assert config.http.listen == ListenAddress("0.0.0.0", 8080) and config.http.token is None


def test_spec_example_is_the_one_in_the_docs() -> None:
    docs = (ROOT / "docs" / "configuration.md").read_text()
    assert SPEC_EXAMPLE.read_text().strip() in docs


def test_minimal_config_defaults() -> None:
    config = load_config_text(
        "buses:\n"
        "  - {name: a, port: /dev/ttyS0, baudrate: 9600, protocol: native,\n"
        "     sensors: [{name: s, series: imu}]}\n"
    )
    assert config.gateway_id == socket.gethostname()
    assert config.modbus is None and config.mqtt is None and config.http is None
    assert config.interfaces() == []
    bus = config.buses[0]
    assert (bus.timeout_ms, bus.retries, bus.rs485) == (None, 1, False)
    sensor = bus.sensors[0]
    assert sensor.series is Series.IMU
    assert (sensor.address, sensor.unit_id, sensor.poll_hz, sensor.stream_hz) == (0, 1, 10, 0)
    assert (sensor.stale_after_ms, sensor.raw_unit_id) == (1000, None)


def test_section_defaults() -> None:
    config = config_from_dict(base(modbus={}, mqtt={}, http={}), env={})
    assert config.modbus == ModbusConfig(
        listen=ListenAddress("0.0.0.0", 502), allow_writes=False,
        allow_from=[ipaddress.ip_network("0.0.0.0/0"), ipaddress.ip_network("::/0")],
        max_connections=100, idle_timeout_s=60,
    )
    mqtt = config.mqtt
    assert mqtt is not None
    assert (mqtt.url, mqtt.base_topic, mqtt.qos, mqtt.retain, mqtt.per_field_topics) == (
        "mqtt://localhost:1883", "imu", 0, True, False)
    assert (mqtt.min_interval_ms, mqtt.homeassistant_discovery, mqtt.allow_commands) == (
        0, False, False)
    assert (mqtt.protocol, mqtt.client_id, mqtt.username, mqtt.password) == (
        "3.1.1", None, None, None)
    assert config.http == HttpConfig(listen=ListenAddress("0.0.0.0", 8080), token=None,
                                     allow_commands=False, read_token_required=False)
    assert config.interfaces() == ["modbus", "mqtt", "http"]


def test_address_defaults_per_protocol() -> None:
    config = config_from_dict(base(), env={})
    assert [s.address for s in config.buses[0].sensors] == [0]
    assert [s.address for s in config.buses[1].sensors] == [1, 2]
    assert [s.unit_id for _, s in config.iter_sensors()] == [1, 2, 3]


def test_two_defaulted_modbus_addresses_collide() -> None:
    data = base()
    del data["buses"][1]["sensors"][1]["address"]
    assert only_problem(data) == (
        "buses[1].sensors[1].address: address 1 is already used by buses[1].sensors[0]")


def test_unit_ids_numbered_across_buses_skipping_taken_ones() -> None:
    data = base()
    data["buses"][1]["sensors"].append({"name": "tip", "series": "AH", "address": 3,
                                        "unit_id": 1})
    data["buses"][0]["sensors"].append({"name": "cab", "series": "VG", "address": 1,
                                        "unit_id": 3})
    config = config_from_dict(data, env={})
    ids = {s.name: s.unit_id for _, s in config.iter_sensors()}
    assert ids == {"boom": 2, "cab": 3, "arm": 4, "base": 5, "tip": 1}


def test_raw_unit_ids_are_skipped_by_default_numbering() -> None:
    data = with_sensor(1, 1, raw_unit_id=2)
    config = config_from_dict(data, env={})
    assert [s.unit_id for _, s in config.iter_sensors()] == [1, 3, 4]


def test_series_and_protocol_are_case_insensitive() -> None:
    data = with_sensor(0, 0, series="mins")
    data["buses"][1]["protocol"] = "MODBUS"
    config = config_from_dict(data, env={})
    assert config.buses[0].sensors[0].series is Series.MINS
    assert config.buses[1].protocol is WireProtocol.MODBUS


def test_pyserial_urls_and_listen_forms() -> None:
    for port in ("socket://h:1", "rfc2217://10.1.1.1:2217", "loop://", "/dev/serial/by-id/x"):
        config_from_dict(with_bus(0, port=port), env={})
    config = config_from_dict(base(modbus={"listen": "[::]:1502"},
                                   http={"listen": "127.0.0.1:0"}), env={})
    assert config.modbus is not None and config.http is not None
    assert config.modbus.listen is not None
    assert (config.modbus.listen.host, config.modbus.listen.port) == ("::", 1502)
    assert str(config.modbus.listen) == "[::]:1502"
    assert config.http.listen == ("127.0.0.1", 0)


def test_streaming_rates_accepted() -> None:
    config_from_dict(with_sensor(0, 0, stream_hz=500), env={})
    config_from_dict(with_sensor(1, 0, stream_hz=0.5), env={})


def test_allow_from_is_not_strict_and_allows() -> None:
    config = config_from_dict(base(modbus={"allow_from": ["192.168.1.7/24", "fd00::/8"]}),
                              env={})
    modbus = config.modbus
    assert modbus is not None
    assert modbus.allow_from == [ipaddress.ip_network("192.168.1.0/24"),
                                 ipaddress.ip_network("fd00::/8")]
    assert modbus.allows("192.168.1.200") and modbus.allows("::ffff:192.168.1.3")
    assert modbus.allows("fd12::1") and not modbus.allows("10.0.0.1")


def test_mqtt_url_forms() -> None:
    assert MqttConfig(url="mqtts://broker").brokers[0].port == 8883
    assert MqttConfig(url="mqtts://broker").tls
    assert MqttConfig(url="mqtt://broker:1999").brokers[0].port == 1999
    assert MqttConfig(protocol=5).protocol == "5"  # type: ignore[arg-type]


def test_mqtt_url_may_list_a_clusters_nodes() -> None:
    mqtt = MqttConfig(url=["mqtts://n1", "mqtts://n2:8884", "mqtts://n3"])
    assert [str(b) for b in mqtt.brokers] == ["n1:8883", "n2:8884", "n3:8883"]
    assert mqtt.tls


@pytest.mark.parametrize(("urls", "problem"), [
    ([], "at least one broker"),
    (["mqtt://a", "mqtts://b"], "one scheme for every broker"),
    (["mqtt://a", "mqtt://a"], "names a broker twice"),
    (["mqtt://a", "http://b"], 'not "http://b"'),
])
def test_a_bad_broker_list_is_refused_with_its_reason(urls: list[str], problem: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(problem)):
        config_from_dict(base(mqtt={"url": urls}), env={})


def test_ca_file_with_mqtts(tmp_path: Path) -> None:
    ca = tmp_path / "ca.pem"
    ca.write_text("x")
    config = config_from_dict(base(mqtt={"url": "mqtts://b", "ca_file": str(ca)}), env={})
    assert config.mqtt is not None and config.mqtt.ca_file == str(ca)


def test_timeout_ms_is_optional_and_positive() -> None:
    assert config_from_dict(with_bus(0), env={}).buses[0].timeout_ms is None  # learned
    assert config_from_dict(with_bus(0, timeout_ms=7), env={}).buses[0].timeout_ms == 7


def test_models_are_frozen_and_dump_to_json_names() -> None:
    config = config_from_dict(base(), env={})
    with pytest.raises(ValueError, match="frozen"):
        config.buses[0].sensors[0].poll_hz = 3
    dumped = config.model_dump(mode="json")
    assert dumped["buses"][1]["protocol"] == "modbus"
    assert dumped["buses"][0]["sensors"][0]["series"] == "AH"
    assert hash(config.buses[0].sensors[0])


def test_built_in_python_gets_the_same_defaults() -> None:
    config = GatewayConfig(gateway_id="demo", buses=[
        BusConfig(name="a", port="loop://", baudrate=9600, protocol=WireProtocol.NATIVE,
                  sensors=[SensorConfig(name="boom", series=Series.AH)]),
        BusConfig(name="b", port="loop://x", baudrate=9600, protocol=WireProtocol.MODBUS,
                  sensors=[SensorConfig(name="arm", series=Series.VG)]),
    ])
    assert [(s.address, s.unit_id) for _, s in config.iter_sensors()] == [(0, 1), (1, 2)]
    with pytest.raises(ConfigError, match=r"buses\[1\]\.name: \"a\" is already used"):
        GatewayConfig(buses=[config.buses[0], config.buses[1].model_copy(update={"name": "a"})])


def test_an_alarm_as_the_issue_writes_it() -> None:
    """docs/alarms.md's example, into the row the alarms evaluate."""
    from imu_gateway.alarms import AlarmRow, Severity

    config = config_from_dict(with_sensor(0, 0, alarms=[{
        "name": "boom_lean", "field": "pitch", "above": 5.0, "hysteresis": 0.5,
        "on_delay_s": 2, "off_delay_s": 0, "severity": "Warning", "latch": False}]), env={})
    (alarm,) = config.buses[0].sensors[0].alarms
    assert alarm.row("boom") == AlarmRow("boom", "boom_lean", "pitch", 5.0, None, 0.5, 2.0,
                                         0.0, Severity.WARNING, False)
    assert config.buses[1].sensors[0].alarms == () and config.alarm_journal is None
    dumped = config.buses[0].sensors[0].model_dump(mode="json")["alarms"][0]
    assert dumped["severity"] == "warning"


# -------------------------------------------------------------- one rule each

RULES: list[tuple[str, dict[str, Any], str]] = [
    ("gateway_id", base(gateway_id="lab 1"),
     'gateway_id: must match [A-Za-z0-9_.-]+ (it is part of MQTT topics), not "lab 1"'),
    ("no buses", base(buses=[]), "buses: must not be empty"),
    ("buses not a list", base(buses="line-a"), 'buses: must be a list, not "line-a"'),
    ("bus name", with_bus(0, name="Line A"),
     'buses[0].name: must match [a-z0-9_-]+ (lower-case letters, digits, _ and -), '
     'not "Line A"'),
    ("port scheme", with_bus(0, port="tcp://h:1"),
     'buses[0].port: unknown URL scheme "tcp": give a device path such as /dev/ttyUSB0 or '
     "a pyserial URL (socket://host:port, rfc2217://host:port, loop://)"),
    ("socket needs port", with_bus(0, port="socket://h"),
     'buses[0].port: must be socket://host:port, not "socket://h"'),
    ("empty port", with_bus(0, port=""), "buses[0].port: must not be empty"),
    ("baudrate", with_bus(0, baudrate=1234),
     "buses[0].baudrate: must be one of 2400, 4800, 9600, 19200, 38400, 57600, 115200, "
     "460800, not 1234"),
    ("protocol", with_bus(0, protocol="can"),
     'buses[0].protocol: must be one of native, modbus, not "can"'),
    ("timeout_ms", with_bus(0, timeout_ms=0), "buses[0].timeout_ms: must be > 0, not 0"),
    ("retries", with_bus(0, retries=11), "buses[0].retries: must be 0-10, not 11"),
    ("retries negative", with_bus(0, retries=-1), "buses[0].retries: must be 0-10, not -1"),
    ("rs485", with_bus(0, rs485="maybe"),
     'buses[0].rs485: must be true or false, not "maybe"'),
    ("no sensors", with_bus(0, sensors=[]), "buses[0].sensors: must not be empty"),
    ("missing sensors", {"buses": [{k: v for k, v in NATIVE_BUS.items() if k != "sensors"}]},
     "buses[0].sensors: required"),
    ("missing port", {"buses": [{k: v for k, v in NATIVE_BUS.items() if k != "port"}]},
     "buses[0].port: required"),
    ("sensor name", with_sensor(0, 0, name="Boom!"),
     'buses[0].sensors[0].name: must match [a-z0-9_-]+ (lower-case letters, digits, _ and -), '
     'not "Boom!"'),
    ("series", with_sensor(0, 0, series="XY"),
     'buses[0].sensors[0].series: must be one of IMU, VG, AH, MINS, not "XY"'),
    ("null series", with_sensor(0, 0, series=None),
     "buses[0].sensors[0].series: must be one of IMU, VG, AH, MINS, not null"),
    ("missing series", base(buses=[NATIVE_BUS | {"sensors": [{"name": "s"}]}]),
     "buses[0].sensors[0].series: required"),
    ("native address", with_sensor(0, 0, address=256),
     "buses[0].sensors[0].address: must be 0-255 on a native bus, not 256"),
    ("modbus address 0", with_sensor(1, 0, address=0),
     "buses[1].sensors[0].address: must be 1-247 on a modbus bus, not 0"),
    ("modbus address 248", with_sensor(1, 1, address=248),
     "buses[1].sensors[1].address: must be 1-247 on a modbus bus, not 248"),
    ("address float", with_sensor(0, 0, address=1.5),
     "buses[0].sensors[0].address: must be a whole number, not 1.5"),
    ("unit_id", with_sensor(0, 0, unit_id=248),
     "buses[0].sensors[0].unit_id: must be 1-247, not 248"),
    ("poll_hz", with_sensor(0, 0, poll_hz=-1),
     "buses[0].sensors[0].poll_hz: must be >= 0, not -1"),
    ("poll_hz text", with_sensor(0, 0, poll_hz="fast"),
     'buses[0].sensors[0].poll_hz: must be a number, not "fast"'),
    ("stream_hz negative", with_sensor(0, 0, stream_hz=-5),
     "buses[0].sensors[0].stream_hz: must be >= 0, not -5"),
    ("native stream rate", with_sensor(0, 0, stream_hz=30),
     "buses[0].sensors[0].stream_hz: must be 0 or one of 5, 10, 20, 25, 50, 100, 200, 500 "
     "on a native bus, not 30"),
    ("modbus stream too fast", with_sensor(1, 0, stream_hz=200),
     "buses[1].sensors[0].stream_hz: on a modbus bus the output interval "
     "round(1000/stream_hz) must be 10-65535 ms (stream_hz about 0.016-100), not 200"),
    ("modbus stream too slow", with_sensor(1, 0, stream_hz=0.01),
     "buses[1].sensors[0].stream_hz: on a modbus bus the output interval "
     "round(1000/stream_hz) must be 10-65535 ms (stream_hz about 0.016-100), not 0.01"),
    ("stale_after_ms", with_sensor(0, 0, stale_after_ms=0),
     "buses[0].sensors[0].stale_after_ms: must be > 0, not 0"),
    ("raw_unit_id range", with_sensor(1, 0, raw_unit_id=0),
     "buses[1].sensors[0].raw_unit_id: must be 1-247, not 0"),
    ("raw_unit_id on native", with_sensor(0, 0, raw_unit_id=100),
     "buses[0].sensors[0].raw_unit_id: only for sensors on a modbus bus; buses[0] is native"),
    ("sensor not a mapping", base(buses=[NATIVE_BUS | {"sensors": ["boom"]}]),
     'buses[0].sensors[0]: must be a mapping (key: value), not "boom"'),
    ("unknown sensor key", with_sensor(0, 0, pol_hz=5),
     "buses[0].sensors[0].pol_hz: unknown key (allowed: name, series, address, unit_id, "
     "poll_hz, stream_hz, stale_after_ms, raw_unit_id, alarms); did you mean poll_hz?"),
    ("unknown top key", base(mqqt={}),
     "mqqt: unknown key (allowed: gateway_id, buses, modbus, mqtt, http, opcua, alarm_journal, "
     "capture, hand_over_ms); "
     "did you mean mqtt?"),
    ("unknown bus key", with_bus(0, baud=9600),
     "buses[0].baud: unknown key (allowed: name, port, baudrate, protocol, timeout_ms, "
     "retries, trace, rs485, sensors); did you mean baudrate?"),
    ("alarm name", with_sensor(0, 0, alarms=[{"name": "Lean", "field": "pitch", "above": 5}]),
     "buses[0].sensors[0].alarms[0].name: must match [a-z0-9_]+ (lower-case letters, digits "
     'and _: it is a topic level and a metric name), not "Lean"'),
    ("alarm named communication", with_sensor(0, 0, alarms=[
        {"name": "communication", "field": "pitch", "above": 5}]),
     "buses[0].sensors[0].alarms[0].name: communication is the built-in alarm of every "
     "sensor (stale or offline); give this one another name"),
    ("alarm name twice", with_sensor(0, 0, alarms=[
        {"name": "lean", "field": "pitch", "above": 5},
        {"name": "lean", "field": "roll", "above": 5}]),
     'buses[0].sensors[0]: alarms[1].name: "lean" is already used by alarms[0]'),
    ("capture on an alarm nobody has", {**with_sensor(0, 0, alarms=[
        {"name": "lean", "field": "pitch", "above": 5}]),
        "capture": {"dir": "/tmp", "on_alarms": ["lean", "laen"]}},
     "capture.on_alarms[1]: no sensor has an alarm 'laen' (its alarms: communication, lean)"),
    ("alarm field the series lacks", with_sensor(1, 0, alarms=[
        {"name": "north", "field": "mag_x", "above": 0.5}]),
     'buses[1].sensors[0]: alarms[0].field: series VG does not measure "mag_x" (its fields: '
     "pitch roll yaw accel_x accel_y accel_z gyro_x gyro_y gyro_z q0 q1 q2 q3 tilt "
     "tilt_direction vibration)"),
    ("alarm without a limit", with_sensor(0, 0, alarms=[{"name": "lean", "field": "pitch"}]),
     "buses[0].sensors[0].alarms[0]: needs above, below or both (a band): the limit it "
     "raises at"),
    ("alarm band upside down", with_sensor(0, 0, alarms=[
        {"name": "lean", "field": "pitch", "above": -5, "below": 5}]),
     "buses[0].sensors[0].alarms[0]: below (5) must be less than above (-5): the alarm is "
     "active outside the band between them"),
    ("alarm band closed by hysteresis", with_sensor(0, 0, alarms=[
        {"name": "lean", "field": "pitch", "above": 5, "below": -5, "hysteresis": 5}]),
     "buses[0].sensors[0].alarms[0]: hysteresis 5 closes the band -5..5: an active alarm "
     "could never clear; make it smaller than half the band"),
    ("alarm hysteresis", with_sensor(0, 0, alarms=[
        {"name": "lean", "field": "pitch", "above": 5, "hysteresis": -0.5}]),
     "buses[0].sensors[0].alarms[0].hysteresis: must be >= 0, not -0.5"),
    ("alarm delay", with_sensor(0, 0, alarms=[
        {"name": "lean", "field": "pitch", "above": 5, "off_delay_s": -1}]),
     "buses[0].sensors[0].alarms[0].off_delay_s: must be >= 0, not -1"),
    ("alarm severity", with_sensor(0, 0, alarms=[
        {"name": "lean", "field": "pitch", "above": 5, "severity": "fatal"}]),
     'buses[0].sensors[0].alarms[0].severity: must be one of info, warning, critical, '
     'not "fatal"'),
    ("alarm journal folder", base(alarm_journal="/nonexistent/alarms.jsonl"),
     "alarm_journal: no such folder: /nonexistent (for /nonexistent/alarms.jsonl); create "
     "it first"),
    ("listen no port", base(modbus={"listen": "0.0.0.0"}),
     'modbus.listen: must be "host:port", e.g. "0.0.0.0:502" or "[::]:502", not "0.0.0.0"'),
    ("listen port range", base(http={"listen": "0.0.0.0:65536"}),
     "http.listen: port must be 0-65535, not 65536"),
    ("listen ipv6 brackets", base(modbus={"listen": "::1:502"}),
     'modbus.listen: an IPv6 host goes in brackets, e.g. "[::]:502", not "::1:502"'),
    ("allow_from", base(modbus={"allow_from": ["10.0.0.0/8", "intranet"]}),
     'modbus.allow_from[1]: must be an IPv4 or IPv6 network such as 10.0.0.0/8, '
     'not "intranet"'),
    ("allow_writes", base(modbus={"allow_writes": "sometimes"}),
     'modbus.allow_writes: must be true or false, not "sometimes"'),
    ("max_connections", base(modbus={"max_connections": 0}),
     "modbus.max_connections: must be > 0, not 0"),
    ("mqtt scheme", base(mqtt={"url": "tcp://broker:1883"}),
     'mqtt.url: must be mqtt://host[:port] or mqtts://host[:port], not "tcp://broker:1883"'),
    ("mqtt credentials in url", base(mqtt={"url": "mqtt://u:secret@broker"}),
     "mqtt.url: must not hold credentials: use the username and password keys"),
    ("mqtt qos", base(mqtt={"qos": 3}), "mqtt.qos: must be 0-2, not 3"),
    ("mqtt protocol", base(mqtt={"protocol": "3.1"}),
     'mqtt.protocol: must be "3.1.1" or 5, not "3.1"'),
    ("mqtt min interval", base(mqtt={"min_interval_ms": -1}),
     "mqtt.min_interval_ms: must be >= 0, not -1"),
    ("mqtt base_topic", base(mqtt={"base_topic": "imu/#"}),
     'mqtt.base_topic: must not contain the MQTT wildcards + or #, not "imu/#"'),
    ("mqtt password alone", base(mqtt={"password": "pw"}), "mqtt.password: needs a username"),
    ("mqtt ca_file missing", base(mqtt={"url": "mqtts://b", "ca_file": "/no/such/ca.pem"}),
     "mqtt.ca_file: no such file: /no/such/ca.pem"),
    ("mqtt password not echoed", base(mqtt={"username": "u", "password": ["x"]}),
     "mqtt.password: must be a string"),
    ("mqtt unknown key", base(mqtt={"topic": "x"}),
     "mqtt.topic: unknown key (allowed: url, username, password, ca_file, certfile, keyfile, "
     "base_topic, qos, retain, per_field_topics, min_interval_ms, homeassistant_discovery, "
     "homeassistant_min_interval_ms, homeassistant_url, allow_commands, protocol, "
     "client_id, deadband, queue_size, backfill, backfill_per_s, state_expiry_s, "
     "discovery_prefix, sparkplug); did you mean base_topic?"),
    ("mqtt deadband of an unknown field", base(mqtt={"deadband": {"pich": 0.1}}),
     'mqtt.deadband: unknown field "pich" (fields: pitch roll yaw accel_x accel_y accel_z '
     "gyro_x gyro_y gyro_z mag_x mag_y mag_z q0 q1 q2 q3 tilt tilt_direction vibration; or a "
     "group: angles accel gyro mag quaternion tilt vibration)"),
    ("mqtt negative deadband", base(mqtt={"deadband": {"angles": -1}}),
     "mqtt.deadband.angles: input should be greater than or equal to 0"),
    ("http commands need a token", base(http={"allow_commands": True}),
     "http.allow_commands: needs http.token, http.tokens or http.users (the credentials "
     "clients must send)"),
    ("http read token needs a token", base(http={"read_token_required": True}),
     "http.read_token_required: needs http.token, http.tokens or http.users (the "
     "credentials clients must send)"),
    ("http empty token", base(http={"token": ""}), "http.token: must not be empty"),
    ("http user's role unknown", base(http={"users": {"ann": {"role": "root",
                                                              "password": A_HASH}}}),
     "http.users.ann.role: input should be 'viewer', 'operator' or 'admin'"),
    ("http user's password not hashed", base(http={"users": {"ann": {
        "role": "admin", "password": "hunter2"}}}),
     "http.users.ann.password: not a password hash (scrypt$n$r$p$salt$hash): make one "
     "with `imu-gateway hash-password`"),
    ("http tokens as a map", base(http={"tokens": {"abc": "viewer"}}),
     "http.tokens: must be a list, not a mapping"),
    ("http token twice", base(http={"tokens": [{"token": "a", "role": "viewer"},
                                               {"token": "a", "role": "admin"}]}),
     "http.tokens: the same token twice (each token has one role)"),
    ("http session of no minutes", base(http={"session_minutes": 0}),
     "http.session_minutes: must be 1-10080, not 0"),
    ("section not a mapping", base(http="on"),
     'http: must be a mapping (key: value), not "on"'),
    ("missing buses", {"gateway_id": "x"}, "buses: required"),
    ("string field given a boolean", with_bus(0, name=True),
     "buses[0].name: must be a string (put it in quotes), not true"),
    ("nan", with_sensor(0, 0, poll_hz=float("nan")),
     "buses[0].sensors[0].poll_hz: must be a finite number, not NaN"),
]


@pytest.mark.parametrize(("data", "expected"), [(d, e) for _, d, e in RULES],
                         ids=[name for name, _, _ in RULES])
def test_each_rule_fails_with_path_and_message(data: dict[str, Any], expected: str) -> None:
    assert only_problem(data) == expected


def test_certfile_and_keyfile_rules(tmp_path: Path) -> None:
    cert = tmp_path / "c.pem"
    cert.write_text("x")
    plain = base(mqtt={"url": "mqtt://b", "certfile": str(cert)})
    assert only_problem(plain) == "mqtt.certfile: needs an mqtts:// url (TLS)"
    key_alone = base(mqtt={"url": "mqtts://b", "keyfile": str(cert)})
    assert only_problem(key_alone) == "mqtt.keyfile: needs a certfile"


# ------------------------------------------------------------ cross-field rules


def two_native_buses() -> dict[str, Any]:
    second = copy.deepcopy(NATIVE_BUS) | {"name": "line-c", "port": "/dev/ttyUSB1"}
    second["sensors"] = [{"name": "stick", "series": "VG"}]
    return base(buses=[copy.deepcopy(NATIVE_BUS), second])


def test_sensor_names_unique_in_the_whole_gateway() -> None:
    data = two_native_buses()
    data["buses"][1]["sensors"][0]["name"] = "boom"
    assert only_problem(data) == 'buses[1].sensors[0].name: "boom" is already used by ' \
        "buses[0].sensors[0]"


def test_bus_names_and_ports_unique() -> None:
    data = two_native_buses()
    data["buses"][1].update(name="line-a", port="/dev/ttyUSB0")
    assert problems_of(data) == [
        'buses[1].name: "line-a" is already used by buses[0]',
        'buses[1].port: "/dev/ttyUSB0" is already used by buses[0]',
    ]


def test_address_unique_per_bus_but_not_across_buses() -> None:
    data = two_native_buses()
    config_from_dict(data, env={})  # both sensors at address 0, on different buses
    data["buses"][0]["sensors"].append({"name": "jib", "series": "AH", "address": 0})
    assert only_problem(data) == (
        "buses[0].sensors[1].address: address 0 is already used by buses[0].sensors[0]")


def test_unit_ids_unique() -> None:
    data = two_native_buses()
    data["buses"][0]["sensors"][0]["unit_id"] = 7
    data["buses"][1]["sensors"][0]["unit_id"] = 7
    assert only_problem(data) == (
        "buses[1].sensors[0].unit_id: unit id 7 is already used by buses[0].sensors[0].unit_id")


def test_raw_unit_id_distinct_from_unit_ids_and_each_other() -> None:
    data = base()
    sensors = data["buses"][1]["sensors"]
    sensors[0].update(unit_id=10, raw_unit_id=11)
    sensors[1].update(unit_id=11, raw_unit_id=10)
    sensors.append({"name": "tip", "series": "AH", "address": 3, "raw_unit_id": 10})
    assert problems_of(data) == [
        "buses[1].sensors[1].unit_id: unit id 11 is already used by "
        "buses[1].sensors[0].raw_unit_id",
        "buses[1].sensors[1].raw_unit_id: unit id 10 is already used by "
        "buses[1].sensors[0].unit_id",
        "buses[1].sensors[2].raw_unit_id: unit id 10 is already used by "
        "buses[1].sensors[0].unit_id",
    ]


def test_raw_unit_id_same_as_own_unit_id() -> None:
    data = with_sensor(1, 0, unit_id=5, raw_unit_id=5)
    assert only_problem(data) == (
        "buses[1].sensors[0].raw_unit_id: unit id 5 is already used by "
        "buses[1].sensors[0].unit_id")


def test_one_streaming_sensor_per_bus() -> None:
    data = base()
    data["buses"][0]["sensors"] = [
        {"name": "a", "series": "AH", "address": 1, "stream_hz": 50},
        {"name": "b", "series": "AH", "address": 2, "stream_hz": 0},
        {"name": "c", "series": "AH", "address": 3, "stream_hz": 100},
        {"name": "d", "series": "AH", "address": 4, "stream_hz": 5},
    ]
    data["buses"][1]["sensors"][1]["stream_hz"] = 10  # another bus may have its own
    assert problems_of(data) == [
        "buses[0].sensors[2].stream_hz: only one sensor per bus may stream; "
        "buses[0].sensors[0] already does",
        "buses[0].sensors[3].stream_hz: only one sensor per bus may stream; "
        "buses[0].sensors[0] already does",
    ]


# --------------------------------------------------------- all problems at once


def test_several_problems_all_listed() -> None:
    data = two_native_buses()
    data["buses"][0]["baudrate"] = 1000
    data["buses"][0]["sensors"][0]["series"] = "XY"
    data["buses"][0]["sensors"].append({"name": "cab", "series": "AH", "address": 1})
    data["buses"][1]["sensors"][0]["poll_hz"] = -2
    data["buses"][1]["sensors"].append({"name": "cab", "series": "AH", "address": 1,
                                        "stream_hz": 3})
    data["buses"][1]["colour"] = "red"
    data["mqtt"] = {"qos": 5}
    assert problems_of(data) == [
        "buses[0].baudrate: must be one of 2400, 4800, 9600, 19200, 38400, 57600, 115200, "
        "460800, not 1000",
        'buses[0].sensors[0].series: must be one of IMU, VG, AH, MINS, not "XY"',
        "buses[1].sensors[0].poll_hz: must be >= 0, not -2",
        "buses[1].colour: unknown key (allowed: name, port, baudrate, protocol, timeout_ms, "
        "retries, trace, rs485, sensors)",
        "mqtt.qos: must be 0-2, not 5",
        # the cross-field checks still run on every part that is valid on its own
        'buses[1].sensors[1].name: "cab" is already used by buses[0].sensors[1]',
        "buses[1].sensors[1].stream_hz: must be 0 or one of 5, 10, 20, 25, 50, 100, 200, 500 "
        "on a native bus, not 3",
    ]


def test_cross_problems_reported_with_field_problems() -> None:
    data = two_native_buses()
    data["buses"][1]["sensors"][0]["name"] = "boom"      # duplicate name (cross-field)
    data["buses"][1]["sensors"].append({"name": "x", "series": "VG", "address": 999})
    data["buses"][0]["retries"] = 99                     # field error on the other bus
    assert problems_of(data) == [
        "buses[0].retries: must be 0-10, not 99",
        'buses[1].sensors[0].name: "boom" is already used by buses[0].sensors[0]',
        "buses[1].sensors[1].address: must be 0-255 on a native bus, not 999",
    ]


# ------------------------------------------------------------------ environment


def spec_text() -> str:
    return SPEC_EXAMPLE.read_text()


def test_env_substitution() -> None:
    text = spec_text().replace("  base_topic: imu", "  base_topic: ${TOPIC}/x\n"
                               "  username: ${MQTT_USER}\n  password: ${MQTT_PASSWORD}")
    text = text.replace("baudrate: 9600", "baudrate: ${BAUD}")
    env = {"TOPIC": "plant", "MQTT_USER": "gw", "MQTT_PASSWORD": "s3cr${et", "BAUD": "19200"}
    config = load_config_text(text, env=env)
    assert config.mqtt is not None
    assert (config.mqtt.base_topic, config.mqtt.username) == ("plant/x", "gw")
    assert config.mqtt.password == "s3cr${et"  # a value is not expanded again
    assert config.buses[0].baudrate == 19200


def test_env_from_os_environ(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("IMU_TEST_TOKEN", "abc")
    config = config_from_dict(base(http={"token": "${IMU_TEST_TOKEN}"}))
    assert config.http is not None and config.http.token == "abc"


def test_http_roles_the_old_token_is_an_admins_and_hashes_come_from_the_environment(
        ) -> None:
    """``http.token`` of before roles is an admin's token, beside ``http.tokens``; a
    user's hash may be ``${VAR}`` (its ``$`` signs are not references)."""
    old = config_from_dict(base(http={"token": "t0", "allow_commands": True}))
    assert old.http is not None and old.http.roles_of_tokens() == {"t0": "admin"}
    data = base(http={"token": "t0", "tokens": [{"token": "${VIEW}", "role": "viewer"}],
                      "users": {"ann": {"role": "operator", "password": "${ANN_HASH}"}},
                      "read_token_required": True})
    new = config_from_dict(data, env={"VIEW": "v1", "ANN_HASH": A_HASH})
    assert new.http is not None
    assert new.http.roles_of_tokens() == {"v1": "viewer", "t0": "admin"}
    assert new.http.users["ann"].password == A_HASH
    assert verify("correct horse", A_HASH) and not verify("correct horsE", A_HASH)
    only_users = base(http={"users": {"ann": {"role": "admin", "password": A_HASH}},
                            "allow_commands": True})
    assert config_from_dict(only_users).http is not None


def test_hash_password_prints_a_hash_the_config_takes() -> None:
    made = subprocess.run([sys.executable, "-m", "imu_gateway", "hash-password"],
                          input="s3cret pass\n", capture_output=True, text=True, timeout=60,
                          check=False)
    assert made.returncode == 0, made.stderr
    printed = made.stdout.strip()
    assert printed.startswith("scrypt$") and verify("s3cret pass", printed)
    config = config_from_dict(base(http={"users": {"ann": {"role": "viewer",
                                                           "password": printed}}}))
    assert config.http is not None and config.http.users["ann"].role == "viewer"
    empty = subprocess.run([sys.executable, "-m", "imu_gateway", "hash-password"], input="\n",
                           capture_output=True, text=True, timeout=60, check=False)
    assert empty.returncode == 2
    assert empty.stderr == "imu-gateway hash-password: the password is empty\n"


def test_env_unset_is_an_error_at_its_path() -> None:
    data = base(mqtt={"username": "gw", "password": "${MQTT_PASSWORD}"},
                http={"token": "Bearer-${HTTP_TOKEN}", "listen": "${LISTEN}"})
    assert problems_of(data) == [
        "mqtt.password: environment variable MQTT_PASSWORD is not set",
        "http.token: environment variable HTTP_TOKEN is not set",
        "http.listen: environment variable LISTEN is not set",
    ]


def test_env_escape_and_bad_references() -> None:
    config = config_from_dict(base(http={"token": "$${NOT_A_VAR}-$x-${A}"}), env={"A": "1"})
    assert config.http is not None and config.http.token == "${NOT_A_VAR}-$x-1"
    assert only_problem(base(http={"token": "${A"})) == (
        "http.token: unterminated ${ (write $${ for a literal ${)")
    assert only_problem(base(http={"token": "${9X}"})) == (
        'http.token: "${9X}" is not an environment variable reference '
        "(a name is letters, digits and _)")


# -------------------------------------------------------------- file problems


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as caught:
        load_config(tmp_path / "nope.yaml")
    assert caught.value.problems == [f"{tmp_path / 'nope.yaml'}: no such file"]


def test_directory(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as caught:
        load_config(tmp_path)
    assert caught.value.problems == [f"{tmp_path}: is a directory, not a config file"]


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_bytes(b"gateway_id: \xff\n")
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert caught.value.problems == [f"{path}: not UTF-8 text (bad byte at offset 12)"]


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n", "---\n"])
def test_empty_file(text: str) -> None:
    assert only_problem(text) == "test.yaml: empty file: expected a mapping with at least 'buses'"


@pytest.mark.parametrize(("text", "kind"), [
    ("- a\n- b\n", "a list"), ("just words\n", "a string"), ("42\n", "a number"),
])
def test_top_level_not_a_mapping(text: str, kind: str) -> None:
    assert only_problem(text) == (
        f"test.yaml: the top level must be a mapping (key: value), not {kind}")


@pytest.mark.parametrize(("text", "expected"), [
    ("buses: [\n", "test.yaml:2:1: invalid YAML: expected the node content"
     ", but found '<stream end>'"),
    ("gateway_id: a\n  buses: x\n", "test.yaml:2:8: invalid YAML: mapping values are not "
     "allowed here"),
    ("buses:\n\t- x\n", "test.yaml:2:1: invalid YAML: found character '\\t' that cannot "
     "start any token"),
    ("gateway_id: a\ngateway_id: b\n", 'test.yaml:2:1: invalid YAML: duplicate key '
     '"gateway_id" (first given on line 1)'),
    ("mqtt: {url: 'mqtt://a', url: 'mqtt://b'}\n", 'test.yaml:1:25: invalid YAML: '
     'duplicate key "url" (first given on line 1)'),
    ("x: !!python/name:os.system\n", "test.yaml:1:4: invalid YAML: could not determine a "
     "constructor for the tag 'tag:yaml.org,2002:python/name:os.system'"),
])
def test_yaml_syntax_error_with_line_and_column(text: str, expected: str) -> None:
    assert only_problem(text) == expected


def test_yaml_merge_keys_are_not_duplicates() -> None:
    text = (
        "buses:\n"
        "  - &bus {name: a, port: /dev/ttyS0, baudrate: 9600, protocol: native,\n"
        "          sensors: [{name: s, series: AH}]}\n"
        "  - <<: *bus\n"
        "    name: b\n"
        "    port: /dev/ttyS1\n"
        "    sensors: [{name: t, series: AH}]\n"
    )
    config = load_config_text(text)
    assert [bus.name for bus in config.buses] == ["a", "b"]


# ------------------------------------------------------------------ the command


def test_check_config_ok() -> None:
    done = cli("check-config", "-c", str(SPEC_EXAMPLE))
    assert done.returncode == 0, done.stderr
    first, sensor, load, *warnings = done.stdout.splitlines()
    assert first == "config OK: gateway lab-1, 1 bus, 1 sensor; interfaces: modbus, mqtt, http"
    # its two numbers, side by side: the bus address and the Modbus TCP unit
    assert sensor == "sensor boom (AH) on line-a: native address 0, Modbus TCP unit 1"
    # what the rates ask of the line; the example's port is not on this machine
    assert load.startswith("bus line-a at 9600 baud: boom 10/s (poll): wire 0.65 s/s")
    missing = ["warning: bus line-a: the port /dev/ttyUSB0 does not exist now (an adapter "
               "unplugged? a udev name not set up?); the gateway keeps trying to open it"]
    assert warnings == ([] if Path("/dev/ttyUSB0").exists() else missing)
    assert done.stderr == ""


def test_check_config_summary_counts(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    data = base()
    data["modbus"] = {}
    data["http"] = {"token": "t"}
    path.write_text(yaml.safe_dump(data))
    done = cli("check-config", "--config", str(path))
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == "config OK: gateway lab-1, 2 buses, 3 sensors; " \
        "interfaces: modbus, http"


def test_check_config_warns_of_a_modbus_unit_id_without_an_address(tmp_path: Path) -> None:
    """``unit_id: 5`` for a Modbus RTU sensor at address 5 passed and then polled address
    1: check-config says which key is which, and shows the address that will be polled."""
    path = tmp_path / "g.yaml"
    path.write_text("""
buses:
  - {name: rtu, port: /dev/null, protocol: modbus, sensors: [
      {name: tilt, series: VG, unit_id: 5, poll_hz: 1},
      {name: told, series: VG, address: 6, unit_id: 6, poll_hz: 1}]}
  - {name: nat, port: /dev/zero, protocol: native, sensors: [{name: boom, series: AH, unit_id: 7}]}
modbus: {}
""")
    done = cli("check-config", "-c", str(path))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "sensor tilt (VG) on rtu: modbus address 1, Modbus TCP unit 5" in lines
    assert "sensor told (VG) on rtu: modbus address 6, Modbus TCP unit 6" in lines
    warnings = [line for line in lines if line.startswith("warning:")]
    # one: the native sensor's address defaults to 0 as documented; told has both
    assert warnings == [
        "warning: buses[0].sensors[0]: unit_id is the Modbus TCP side; the sensor's RTU "
        'address is `address` (not given, so "tilt" is polled at address 1)']


def test_check_config_lists_every_problem_and_exits_2(tmp_path: Path) -> None:
    path = tmp_path / "g.yaml"
    data = two_native_buses()
    data["buses"][0]["sensors"][0]["series"] = "XY"
    data["buses"][1]["sensors"][0]["name"] = "boom"
    data["buses"][1]["sensors"].append({"name": "boom", "series": "AH", "address": 4})
    data["mqtt"] = {"username": "u", "password": "${IMU_TEST_UNSET_PASSWORD}"}
    path.write_text(yaml.safe_dump(data))
    done = cli("check-config", "-c", str(path))
    assert done.returncode == 2
    assert done.stdout == ""
    assert "Traceback" not in done.stderr
    assert done.stderr.splitlines() == [
        "mqtt.password: environment variable IMU_TEST_UNSET_PASSWORD is not set",
        'buses[0].sensors[0].series: must be one of IMU, VG, AH, MINS, not "XY"',
        # a sensor with a bad series still counts for the uniqueness of its name
        'buses[1].sensors[0].name: "boom" is already used by buses[0].sensors[0]',
        'buses[1].sensors[1].name: "boom" is already used by buses[0].sensors[0]',
    ]


@pytest.mark.parametrize(("content", "expected"), [
    (None, "no such file"),
    ("", "empty file"),
    ("buses: [\n", "invalid YAML"),
    ("- 1\n", "must be a mapping"),
    ("bogus: 1\n", "bogus: unknown key"),
])
def test_check_config_file_problems_one_line_no_traceback(
    tmp_path: Path, content: str | None, expected: str
) -> None:
    path = tmp_path / "g.yaml"
    if content is not None:
        path.write_text(content)
    done = cli("check-config", "-c", str(path))
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    assert expected in done.stderr
    if content != "bogus: 1\n":
        assert len(done.stderr.splitlines()) == 1


def test_check_config_needs_a_file() -> None:
    done = cli("check-config")
    assert done.returncode == 2
    assert "error:" in done.stderr and "Traceback" not in done.stderr


def test_baudrate_defaults_to_the_sensors_factory_rate() -> None:
    data = base()
    del data["buses"][0]["baudrate"]
    assert config_from_dict(data, env={}).buses[0].baudrate == 9600


def test_deadband_of_a_group_applies_to_its_fields_and_a_field_wins() -> None:
    bands = MqttConfig(deadband={"angles": 0.5, "yaw": 2.0, "q0": 0.01}).field_deadbands()
    assert bands == {"pitch": 0.5, "roll": 0.5, "yaw": 2.0, "q0": 0.01}


@pytest.mark.parametrize(("opcua", "message"), [
    ({"allow_commands": True},
     "opcua: anonymous: true with allow_commands: true lets anyone run commands"),
    ({"anonymous": False}, "opcua: anonymous: false needs users, or nobody can log in"),
    ({"listen": "127.0.0.1:0"}, "opcua: listen: port 0 is not for OPC UA"),
])
def test_opcua_access_rules_are_checked(opcua: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError) as failed:
        config_from_dict({"buses": [{"name": "a", "port": "/dev/null", "protocol": "native",
                                     "sensors": [{"name": "s", "series": "AH"}]}],
                          "opcua": opcua}, env={})
    assert any(p.startswith(message) for p in failed.value.problems), failed.value.problems


def test_a_config_ruamel_cannot_read_is_shown_without_its_comments(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The file's text is parsed when first asked for; where ruamel.yaml refuses what
    the config's own reading accepted, the data is that reading's (the config can still
    be shown and saved), and a warning says why."""
    from ruamel.yaml.error import YAMLError

    from imu_gateway.config import loading

    text = "# ours\ngateway_id: plant\nbuses: []\n"
    source = loading.ConfigSource(None, text=text)

    def refuse(text: str) -> Any:
        raise YAMLError("a construct ruamel does not take")

    monkeypatch.setattr(loading, "round_trip_load", refuse)
    with caplog.at_level("WARNING", logger="imu_gateway.config"):
        assert source.data == {"gateway_id": "plant", "buses": []}
    assert "a construct ruamel does not take" in caplog.text
    monkeypatch.undo()
    assert source.data == {"gateway_id": "plant", "buses": []}  # (parsed once)
    fresh = loading.ConfigSource(None, text=text)
    assert fresh.data.ca is not None  # (ruamel's, comments kept)
    fresh.data = {"gateway_id": "other"}
    assert fresh.data == {"gateway_id": "other"}


@pytest.mark.parametrize("style", [
    ("  ", "  - ", "    "),   # the dash 2 in (the examples' style)
    ("    ", "- ", "  "),     # the dash at its parent's column, mappings by 4
    ("  ", "    - ", "      "),
])
def test_a_save_keeps_the_files_own_indentation(tmp_path: Path,
                                                 style: tuple[str, str, str]) -> None:
    """Only what changed changes: a user diffing the saved file against its ``.bak``
    sees the one line (ruamel's default moved every list's dash to its parent's column)."""
    from imu_gateway.config.loading import ConfigSource, save_atomically

    key, dash, entry = style
    text = (f"# the plant's gateway\nmqtt:\n{key}url: mqtt://broker:1883  # ours\n"
            f"buses:\n{dash}name: line-a\n{entry}port: /dev/ttyUSB0\n{entry}sensors:\n"
            f"{entry}{dash}name: boom\n{entry}{entry}series: AH\n")
    path = tmp_path / "gateway.yaml"
    path.write_text(text)
    data = ConfigSource.read(path).data
    data["buses"][0]["port"] = "/dev/ttyUSB1"
    save_atomically(path, data)
    assert path.read_text() == text.replace("ttyUSB0", "ttyUSB1")
    assert (tmp_path / "gateway.yaml.bak").read_text() == text
