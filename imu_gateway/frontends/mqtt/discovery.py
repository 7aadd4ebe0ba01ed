"""Home Assistant's MQTT discovery configs (docs/mqtt.md), as pure functions.

The gateway is a device of its own: a connectivity binary sensor (its status topic),
and per bus its utilisation, exchanges a second and errors, as diagnostic entities.
Each sensor is a device ``via_device`` the gateway, named with the gateway id (two
gateways with a sensor ``boom`` give two devices).  It has:

* one entity per measured field, from the value-group table (unit, display
  precision); the quaternion's are disabled by default;
* its status, ``ts`` and ``seq`` as attributes, and ``unavailable`` unless its status
  is ``ok`` (a stale reading never looks fresh), besides the gateway's and its own
  availability;
* its readings a second, learned latency and errors as diagnostic entities;
* per alarm (its configured ones, then ``communication``), a ``problem`` binary sensor,
  on while the alarm is active, with the alarm's state as attributes, and with
  ``allow_commands`` a button that acknowledges it; both available while the gateway
  is online (the communication alarm is on exactly when the sensor is not);
* with ``allow_commands``, its commands as entities, from the catalogue rows that
  have a register: a button for a command without arguments, a select for a choice,
  a number for an angle, each showing the known setting.

The entities read the sensor's Home Assistant state topic (``…/{sensor}/ha``), which
has its own throttle, ``homeassistant_min_interval_ms``: Home Assistant records each
state change, and a 100 Hz stream would flood its database.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from ... import __version__
from ...commands import CATALOGUE, CommandSpec, commands_for, resolution
from ...config import GatewayConfig, SensorConfig
from ...model import CAPABILITIES, VALUE_GROUPS, Group, WireProtocol
from ...normalise import member_name
from .topics import HA_LEAF, SETTINGS_LEAF, Topics, alarm_names

Config = dict[str, Any]
ORIGIN = {"name": "imu-gateway", "sw_version": __version__}


@dataclass(frozen=True, slots=True)
class Setup:
    """What the discovery configs are made from."""

    topics: Topics
    sensors: Mapping[str, tuple[SensorConfig, WireProtocol]]
    buses: tuple[str, ...]
    commands: bool  # mqtt.allow_commands
    configuration_url: str | None  # the dashboard

    @property
    def gateway_id(self) -> str:
        return f"imu-gateway_{self.topics.gateway_id}".replace(".", "_")


def setup_of(gateway: GatewayConfig, topics: Topics) -> Setup:
    """The discovery's inputs, from the gateway's config."""
    assert gateway.mqtt is not None
    url = gateway.mqtt.homeassistant_url
    if url is None and gateway.http is not None:
        host, port = gateway.http.listen
        if host in ("", "0.0.0.0", "::"):
            host = socket.gethostname()  # listening everywhere: the box's own name
        url = f"http://{host}:{port}/"
    return Setup(topics, {s.name: (s, b.protocol) for b, s in gateway.iter_sensors()},
                 tuple(b.name for b in gateway.buses), gateway.mqtt.allow_commands, url)


def discovery_configs(setup: Setup) -> dict[str, Config]:
    """Topic -> discovery payload, for every entity of the gateway and its sensors."""
    out = dict(_gateway_entities(setup))
    for name, (sensor, protocol) in setup.sensors.items():
        device = _sensor_device(setup, name, sensor)
        out.update(_measured(setup, name, sensor, device))
        out.update(_sensor_diagnostics(setup, name, device))
        out.update(_alarm_entities(setup, name, sensor, device))
        if setup.commands:
            out.update(_command_entities(setup, name, sensor, protocol, device))
    return out


def _jinja(expression: str) -> str:
    """A Home Assistant template of one expression."""
    return "{{ " + expression + " }}"


def _topic(setup: Setup, component: str, object_id: str) -> str:
    return f"{setup.topics.discovery_prefix}/{component}/{object_id}/config"


def _oid(setup: Setup, *parts: str) -> str:
    # Home Assistant's object ids allow [a-zA-Z0-9_-]; a gateway id may hold dots.
    return "_".join((setup.topics.gateway_id, *parts)).replace(".", "_")


def _gateway_device(setup: Setup) -> Config:
    device: Config = {"identifiers": [setup.gateway_id],
                      "name": f"imu-gateway {setup.topics.gateway_id}",
                      "manufacturer": "imu-gateway", "model": "imu-gateway",
                      "sw_version": __version__}
    if setup.configuration_url:
        device["configuration_url"] = setup.configuration_url
    return device


def _sensor_device(setup: Setup, name: str, sensor: SensorConfig) -> Config:
    return {"identifiers": [_oid(setup, name)],
            "name": f"{setup.topics.gateway_id} {name}",
            "model": f"{sensor.series.name} series", "manufacturer": "imu-gateway",
            "sw_version": __version__, "via_device": setup.gateway_id}


def _gateway_entities(setup: Setup) -> Iterator[tuple[str, Config]]:
    device = _gateway_device(setup)
    yield _topic(setup, "binary_sensor", _oid(setup, "connectivity")), {
        "name": "connectivity", "unique_id": _oid(setup, "connectivity"),
        "state_topic": setup.topics.status, "payload_on": "online", "payload_off": "offline",
        "device_class": "connectivity", "entity_category": "diagnostic",
        "device": device, "origin": ORIGIN}
    diagnostics = setup.topics.diagnostics
    for bus in setup.buses:
        for key, label, extra in _BUS_DIAGNOSTICS:
            oid = _oid(setup, "bus", bus, key)
            yield _topic(setup, "sensor", oid), {
                "name": f"{bus} {label}", "unique_id": oid, "state_topic": diagnostics,
                "value_template": _jinja(f"value_json['buses']['{bus}']['{key}']"),
                "entity_category": "diagnostic", "availability_topic": setup.topics.status,
                "device": device, "origin": ORIGIN, **extra}


# key in the diagnostics JSON, entity name, what else the entity says
_BUS_DIAGNOSTICS: tuple[tuple[str, str, Config], ...] = (
    ("utilisation", "utilisation", {"unit_of_measurement": "%", "state_class": "measurement",
                                    "suggested_display_precision": 1}),
    ("transactions_per_s", "exchanges per second", {"state_class": "measurement",
                                                    "suggested_display_precision": 1}),
    ("errors", "errors", {"state_class": "total_increasing"}),
)
_SENSOR_DIAGNOSTICS: tuple[tuple[str, str, Config], ...] = (
    ("achieved_hz", "readings per second", {"unit_of_measurement": "Hz",
                                            "state_class": "measurement",
                                            "suggested_display_precision": 1}),
    ("latency_ms", "latency", {"unit_of_measurement": "ms", "device_class": "duration",
                               "state_class": "measurement",
                               "suggested_display_precision": 1}),
    ("errors", "errors", {"state_class": "total_increasing"}),
)


def _online(setup: Setup, name: str) -> list[Config]:
    """The gateway's status and the sensor's availability: both ``online``."""
    return [{"topic": setup.topics.status},
            {"topic": setup.topics.sensor(name, "availability")}]


def _availability(setup: Setup, name: str) -> Config:
    """Available while the gateway and the sensor are online and its reading is ``ok``
    (stale or offline: unavailable), with its status, ts and seq as attributes."""
    ha = setup.topics.sensor(name, HA_LEAF)
    return {
        "availability": [*_online(setup, name),
                         {"topic": ha, "value_template":
                          "{{ 'online' if value_json.status == 'ok' else 'offline' }}"}],
        "availability_mode": "all",
        "json_attributes_topic": ha,
        "json_attributes_template": "{{ {'status': value_json.status, 'ts': value_json.ts, "
                                    "'seq': value_json.seq} | tojson }}",
    }


def _measured(setup: Setup, name: str, sensor: SensorConfig,
              device: Config) -> Iterator[tuple[str, Config]]:
    for group, spec in VALUE_GROUPS.items():
        if group not in CAPABILITIES[sensor.series].groups:
            continue
        for field_name in spec.fields:
            payload: Config = {
                "name": field_name.replace("_", " "),
                "unique_id": _oid(setup, name, field_name),
                "state_topic": setup.topics.sensor(name, HA_LEAF),
                "value_template": "{{ value_json." + group.value + "."
                                  + member_name(group, field_name) + " }}",
                "state_class": "measurement",
                "suggested_display_precision": spec.digits,
                **_availability(setup, name),
                "device": device, "origin": ORIGIN,
            }
            if spec.symbol:
                payload["unit_of_measurement"] = spec.symbol
            if group is Group.QUATERNION:  # rarely wanted on a dashboard: there if asked
                payload["enabled_by_default"] = False
            yield setup.topics.discovery(name, field_name), payload


def _sensor_diagnostics(setup: Setup, name: str,
                        device: Config) -> Iterator[tuple[str, Config]]:
    diagnostics = setup.topics.diagnostics
    for key, label, extra in _SENSOR_DIAGNOSTICS:
        oid = _oid(setup, name, "diag", key)
        yield _topic(setup, "sensor", oid), {
            "name": label, "unique_id": oid, "state_topic": diagnostics,
            "value_template": _jinja(f"value_json['sensors']['{name}']['{key}']"),
            "entity_category": "diagnostic", "availability_topic": setup.topics.status,
            "device": device, "origin": ORIGIN, **extra}


#: An alarm's state JSON as a binary sensor's attributes.  Its ``state`` becomes
#: ``alarm_state``: Home Assistant drops an attribute named ``state``.
_ALARM_ATTRIBUTES = _jinja("{'alarm_state': value_json.state, " + ", ".join(
    f"'{key}': value_json.{key}" for key in ("acked", "severity", "field", "value", "limit",
                                             "since", "latch")) + "} | tojson")
#: What Home Assistant's acknowledge button sends: who acknowledged, in the journal, is
#: ``home assistant (mqtt)``.
ACK_PRESS = '{"by": "home assistant"}'


def _alarm_entities(setup: Setup, name: str, sensor: SensorConfig,
                    device: Config) -> Iterator[tuple[str, Config]]:
    """Per alarm a ``problem`` binary sensor and, with commands, an acknowledge button.
    Available while the gateway is: an alarm's state does not depend on the sensor's
    (the communication alarm is on while the sensor is stale or offline)."""
    for alarm in alarm_names(sensor):
        topic, label = setup.topics.alarm(name, alarm), alarm.replace("_", " ")
        oid = _oid(setup, name, "alarm", alarm)
        yield _topic(setup, "binary_sensor", oid), {
            "name": f"{label} alarm", "unique_id": oid, "state_topic": topic,
            "value_template": _jinja("'ON' if value_json.active else 'OFF'"),
            "device_class": "problem", "json_attributes_topic": topic,
            "json_attributes_template": _ALARM_ATTRIBUTES,
            "availability_topic": setup.topics.status, "device": device, "origin": ORIGIN}
        if setup.commands:
            yield _topic(setup, "button", f"{oid}_ack"), {
                "name": f"acknowledge {label}", "unique_id": f"{oid}_ack",
                "command_topic": setup.topics.alarm_ack(name, alarm),
                "payload_press": ACK_PRESS, "availability_topic": setup.topics.status,
                "device": device, "origin": ORIGIN}


def _command_entities(setup: Setup, name: str, sensor: SensorConfig, protocol: WireProtocol,
                      device: Config) -> Iterator[tuple[str, Config]]:
    """The catalogue's commands that have a register and that this sensor has."""
    carried = commands_for(sensor.series, protocol)
    for spec in CATALOGUE.values():
        if spec.register is None or spec.name not in carried:
            continue
        oid = _oid(setup, name, spec.name)
        common: Config = {
            "name": spec.name.replace("_", " "), "unique_id": oid,
            "command_topic": setup.topics.sensor(name, f"cmd/{spec.name}"),
            "entity_category": "config",
            "availability": _online(setup, name),
            "availability_mode": "all", "device": device, "origin": ORIGIN}
        component, specific = _command_entity(setup, name, spec)
        yield _topic(setup, component, oid), {**common, **specific}


def _command_entity(setup: Setup, name: str, spec: CommandSpec) -> tuple[str, Config]:
    """A button, a select or a number, by the command's argument."""
    assert spec.register is not None
    argument = spec.argument
    if argument is None:
        return "button", {"payload_press": "{}"}
    shown: Config = {}
    if spec.register.setting:
        # (.get: a setting not known, after an absence, renders "None", which Home
        # Assistant shows as unknown; a missing key would render "" and log an error)
        shown = {"state_topic": setup.topics.sensor(name, SETTINGS_LEAF),
                 "value_template": _jinja(f"value_json.get('{spec.register.setting}')")}
    command = {"command_template": f'{{"{argument}": ' + _jinja("value | tojson") + "}"}
    if spec.register.codes:
        return "select", {"options": list(spec.register.codes), **command, **shown}
    prop = spec.args.model_json_schema()["properties"][argument]
    step = resolution(spec) or 0.01
    return "number", {"min": prop["minimum"], "max": prop["maximum"], "step": step,
                      "mode": "box", "unit_of_measurement": "°", **command, **shown}
