"""``docs/config-reference.md``, generated from the config schema
(``imu_gateway/config/schema.py``).

Every key of every section, with its type, default and rule, is read from the pydantic
models: a field's ``description`` is its rule, and ``json_schema_extra`` may say what
default (``shown_default``) or type (``shown_type``) to show where pydantic's would
mislead.  ``scripts/config-reference`` writes the file; ``tests/config/test_config_reference.py``
fails while the committed file differs from :func:`markdown`.

Run ``python -m imu_gateway.tools.config_reference`` to print it.
"""

from __future__ import annotations

import enum
import ipaddress
import types
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from ..bus.timing import RTO_INITIAL, RTO_MAX, RTO_MIN
from ..config import (
    BusConfig,
    CaptureConfig,
    GatewayConfig,
    HttpConfig,
    ListenAddress,
    ModbusConfig,
    MqttConfig,
    OpcUaConfig,
    SensorConfig,
    SparkplugConfig,
)
from ..config.schema import AlarmConfig, HttpToken, HttpUser, ModbusTlsConfig

#: (heading, model, what the section is): the order of the document.
SECTIONS: tuple[tuple[str, type[BaseModel], str], ...] = (
    ("top level", GatewayConfig,
     "Only `buses` is required. A section left out (or empty: `http:` with nothing under "
     "it is `null`) turns its interface off; `http: {}` turns it on with every default."),
    ("buses[]", BusConfig, "One serial line each; one bus master owns it."),
    ("buses[].sensors[]", SensorConfig, "The sensors on a line."),
    ("buses[].sensors[].alarms[]", AlarmConfig,
     "A sensor's alarms ([alarms.md](alarms.md)); `name`, `field` and `above` or "
     "`below` are required."),
    ("modbus", ModbusConfig, "The Modbus TCP server ([modbus-tcp.md](modbus-tcp.md))."),
    ("modbus.tls", ModbusTlsConfig,
     "Modbus/TCP Security: mutual TLS, rights by the role in the client's certificate "
     "([modbus-tcp.md](modbus-tcp.md#modbustcp-security-tls)); `certfile`, `keyfile` "
     "and `ca_file` are required. Relative file paths are relative to the gateway's "
     "working directory."),
    ("mqtt", MqttConfig,
     "The MQTT client ([mqtt.md](mqtt.md)). Relative file paths are relative to the "
     "gateway's working directory."),
    ("mqtt.sparkplug", SparkplugConfig,
     "Sparkplug B on the same brokers ([sparkplug.md](sparkplug.md)); `group_id` is "
     "required."),
    ("http", HttpConfig, "The REST API and dashboard ([rest.md](rest.md)); who may "
     "do what: [rest.md](rest.md#roles)."),
    ("http.tokens[]", HttpToken, "A token a program sends, and its role; both required."),
    ("http.users.NAME", HttpUser, "A person who logs in; both required."),
    ("opcua", OpcUaConfig, "The OPC UA server ([opcua.md](opcua.md))."),
    ("capture", CaptureConfig, "Event capture ([alarms.md](alarms.md#captures))."),
)

_NETWORK = (ipaddress.IPv4Network, ipaddress.IPv6Network)


def _extra(field: FieldInfo, key: str) -> str | None:
    extra = field.json_schema_extra
    value = extra.get(key) if isinstance(extra, dict) else None
    return value if isinstance(value, str) else None


def type_name(annotation: Any) -> str:
    """The type of a config value as a user writes it in YAML."""
    origin = get_origin(annotation)
    if origin is Annotated:
        return type_name(get_args(annotation)[0])
    if origin in (Union, types.UnionType):
        args = get_args(annotation)
        if set(args) == set(_NETWORK):
            return "network"
        named = [type_name(a) for a in args if a is not type(None)]
        return " or ".join([*named, "null"] if type(None) in args else named)
    if origin in (list, tuple):  # (a tuple of any length: ``tuple[X, ...]``)
        item = get_args(annotation)[0]
        inner = type_name(item)
        return f"list of {'mappings' if inner == 'mapping' else inner + 's'}"
    if origin is dict:
        return "map"
    if origin is Literal:
        return "string"
    if isinstance(annotation, type):
        if issubclass(annotation, BaseModel):
            return "mapping"
        if issubclass(annotation, bool):
            return "boolean"
        if issubclass(annotation, int):
            return "integer"
        if issubclass(annotation, float):
            return "number"
        if issubclass(annotation, str | enum.Enum | ListenAddress):
            return "string"
    raise TypeError(f"no user-facing name for the type {annotation!r}")


def _value(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    if isinstance(value, int | float):
        return str(value)
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_value(v)}" for k, v in value.items()) + "}"
    return str(value)


def default_text(field: FieldInfo) -> str:
    """The default as the reference shows it: ``required``, ``null``, or the value."""
    shown = _extra(field, "shown_default")
    if shown is not None:
        return shown
    if field.is_required():
        return "required"
    value = field.get_default(call_default_factory=True)
    if value is None or isinstance(value, bool | int | float):
        return _value(value)
    return f"`{_value(value)}`"


def _cell(text: str) -> str:
    # A | inside a cell would end it; a line break would end the row.
    return " ".join(text.replace("|", "\\|").split())


def table(model: type[BaseModel]) -> list[str]:
    lines = ["| key | type | default | rule |", "|---|---|---|---|"]
    for key, field in model.model_fields.items():
        if not field.description:
            raise ValueError(f"{model.__name__}.{key} has no description")
        kind = _extra(field, "shown_type") or type_name(field.annotation)
        lines.append(f"| `{key}` | {_cell(kind)} | {_cell(default_text(field))} | "
                     f"{_cell(field.description)} |")
    return lines


def markdown() -> str:
    """``docs/config-reference.md``."""
    lines = [
        "# Config reference",
        "",
        "Generated from the schema in `imu_gateway/config/schema.py` by "
        "`scripts/config-reference`; "
        "do not edit by hand. [configuration.md](configuration.md) explains the file: "
        "examples, `${VAR}` secrets, error messages and the checks across keys.",
        "",
        "Unknown keys are errors. Numbers may be written as strings (`\"9600\"`, which is "
        "what `${VAR}` gives); floats must be finite and whole numbers whole. Booleans are "
        "YAML booleans.",
    ]
    for heading, model, intro in SECTIONS:
        lines += ["", f"## `{heading}`" if heading != "top level" else "## Top level", "",
                  intro, "", *table(model)]
        if model is BusConfig:
            lines += [
                "",
                "Without `timeout_ms`, each sensor's timeout is learned from its answers "
                "(RFC 6298: smoothed latency + 4 deviations, "
                f"{RTO_MIN * 1000:g}-{RTO_MAX * 1000:g} ms, {RTO_INITIAL * 1000:g} ms "
                "before its first answer); see [bus-master.md](bus-master.md#the-timing-rule-"
                "how-long-to-wait-for-an-answer).",
            ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # pragma: no cover
    print(markdown(), end="")
