"""The config file (docs/configuration.md): a YAML schema, validated at load.

``load_config(path)`` returns a :class:`GatewayConfig` or raises :class:`ConfigError`,
whose ``problems`` are one line each, ``<yaml path>: <message>``
(``buses[0].sensors[1].series: must be one of IMU, VG, AH, MINS, not "XY"``).  Every
problem in the file is listed, not only the first: field errors from pydantic are
converted in one place (:func:`_pydantic_problem`), and the checks that span several
fields (uniqueness, one streaming sensor per bus, what a protocol allows) run on every
part that is valid on its own (:func:`_cross_problems`).

Defaults that depend on context are filled in before validation, so the models always
hold final values: a sensor's ``address`` (0 on a native bus, 1 on a modbus bus) and its
``unit_id`` (1, 2, … in document order across the gateway, skipping the ids taken
explicitly).

Each field's ``description`` is its rule for the user: ``docs/config-reference.md`` is
generated from them (``scripts/config-reference``); ``docs/configuration.md`` is the
narrative.
"""

from __future__ import annotations

import contextlib
import difflib
import ipaddress
import json
import os
import re
import socket
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple, Self, cast, get_args
from urllib.parse import urlsplit

import yaml
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    TypeAdapter,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import ErrorDetails, PydanticCustomError

from .errors import ConfigError
from .model import Group, Series, WireProtocol
from .normalise import FIELD_NAMES, GROUP_FIELDS
from .protocol.native import BAUD_CODES, OUTPUT_RATE_CODES

__all__ = [
    "BusConfig",
    "GatewayConfig",
    "HttpConfig",
    "ListenAddress",
    "ModbusConfig",
    "MqttConfig",
    "SensorConfig",
    "config_from_dict",
    "load_config",
    "load_config_text",
]

BAUD_RATES: tuple[int, ...] = tuple(sorted(BAUD_CODES.values()))
#: Auto-output rates a native sensor has a code for (0 is polled mode).
NATIVE_STREAM_HZ: tuple[int, ...] = tuple(sorted(r for r in OUTPUT_RATE_CODES.values() if r))
#: A Modbus sensor's auto-output interval register (0x1B), in ms.
MODBUS_STREAM_INTERVAL_MS = (10, 65535)
ADDRESS_RANGE: Mapping[WireProtocol, tuple[int, int]] = {
    WireProtocol.NATIVE: (0, 255),
    WireProtocol.MODBUS: (1, 247),
}
DEFAULT_ADDRESS: Mapping[WireProtocol, int] = {WireProtocol.NATIVE: 0, WireProtocol.MODBUS: 1}
UNIT_ID_RANGE = (1, 247)


#: pyserial's URL handlers (serial.serial_for_url).
PYSERIAL_SCHEMES = ("socket", "rfc2217", "loop", "spy", "alt", "hwgrep", "cp2110")
_NAME = re.compile(r"[a-z0-9_-]+")
_GATEWAY_ID = re.compile(r"[A-Za-z0-9_.-]+")
_ENV_REF = re.compile(r"\$\$\{|\$\{([^}]*)\}|\$\{")
_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# Values never echoed in a message.
_SECRET_KEYS = frozenset({"password", "token"})


# --------------------------------------------------------------------------- messages


def _fail(message: str) -> PydanticCustomError:
    # The message travels in the context so that braces in it are never a template.
    return PydanticCustomError("config", "{message}", {"message": message})


def _show(value: object) -> str:
    """A short rendering of a bad value for a message: JSON-like, lists and maps by kind."""
    if isinstance(value, str | int | float | bool) or value is None:
        try:
            text = json.dumps(value, ensure_ascii=False)
        except ValueError:  # pragma: no cover - NaN is allowed by json.dumps
            text = repr(value)
    elif isinstance(value, list | tuple):
        text = "a list"
    elif isinstance(value, Mapping):
        text = "a mapping"
    else:
        text = type(value).__name__
    return text if len(text) <= 60 else text[:57] + "..."


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(value)


def _path(loc: tuple[int | str, ...]) -> str:
    """``('buses', 0, 'sensors', 1, 'series')`` → ``buses[0].sensors[1].series``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += f".{part}" if out else str(part)
    return out


# ------------------------------------------------------------------ field validators


def _between(low: int, high: int) -> AfterValidator:
    def check(value: int) -> int:
        if not low <= value <= high:
            raise _fail(f"must be {low}-{high}, not {value}")
        return value

    return AfterValidator(check)


def _at_least(low: float) -> AfterValidator:
    def check(value: float) -> float:
        if value < low:
            raise _fail(f"must be >= {_number(low)}, not {_number(value)}")
        return value

    return AfterValidator(check)


def _positive(value: float) -> float:
    if value <= 0:
        raise _fail(f"must be > 0, not {_number(value)}")
    return value


def _name(value: str) -> str:
    if not _NAME.fullmatch(value):
        raise _fail(
            f"must match [a-z0-9_-]+ (lower-case letters, digits, _ and -), not {_show(value)}"
        )
    return value


def _gateway_id(value: str) -> str:
    if not _GATEWAY_ID.fullmatch(value):
        raise _fail(f"must match [A-Za-z0-9_.-]+ (it is part of MQTT topics), not {_show(value)}")
    return value


def _not_empty(value: str) -> str:
    if not value:
        raise _fail("must not be empty")
    return value


def _series(value: object) -> Series:
    if isinstance(value, Series):
        return value
    if isinstance(value, str) and value.strip().upper() in Series.__members__:
        return Series[value.strip().upper()]
    raise _fail(f"must be one of {', '.join(s.name for s in Series)}, not {_show(value)}")


def _protocol(value: object) -> WireProtocol:
    if isinstance(value, WireProtocol):
        return value
    if isinstance(value, str) and value.strip().upper() in WireProtocol.__members__:
        return WireProtocol[value.strip().upper()]
    raise _fail(f"must be one of native, modbus, not {_show(value)}")


def _baudrate(value: int) -> int:
    if value not in BAUD_RATES:
        raise _fail(f"must be one of {', '.join(map(str, BAUD_RATES))}, not {value}")
    return value


def _serial_port(value: str) -> str:
    if not value.strip():
        raise _fail("must not be empty")
    if "://" not in value:
        return value  # a device path: /dev/ttyUSB0, /dev/serial/by-id/…, COM3
    scheme = value.split("://", 1)[0].lower()
    if scheme not in PYSERIAL_SCHEMES:
        raise _fail(
            f"unknown URL scheme {_show(scheme)}: give a device path such as /dev/ttyUSB0 "
            "or a pyserial URL (socket://host:port, rfc2217://host:port, loop://)"
        )
    if scheme in ("socket", "rfc2217"):
        parts = urlsplit(value)
        try:
            port = parts.port
        except ValueError:
            port = None
        if not parts.hostname or port is None:
            raise _fail(f"must be {scheme}://host:port, not {_show(value)}")
    return value


def _enum_name(value: Series) -> str:
    return value.name


def _protocol_name(value: WireProtocol) -> str:
    return value.name.lower()


class ListenAddress(NamedTuple):
    """A ``listen`` value: ``"host:port"``; an IPv6 host in brackets (``"[::]:502"``)."""

    host: str
    port: int

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"


def _listen(value: object) -> ListenAddress:
    if isinstance(value, ListenAddress):
        return value
    example = 'must be "host:port", e.g. "0.0.0.0:502" or "[::]:502"'
    if not isinstance(value, str):
        raise _fail(f"{example}, not {_show(value)}")
    host, sep, port = value.strip().rpartition(":")
    if not sep or not host or not port.isdigit():
        raise _fail(f"{example}, not {_show(value)}")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise _fail(f"{_show(host)} in brackets is not an IPv6 address") from None
    elif ":" in host:
        raise _fail(f'an IPv6 host goes in brackets, e.g. "[::]:502", not {_show(value)}')
    if int(port) > 65535:
        raise _fail(f"port must be 0-65535, not {port}")
    return ListenAddress(host, int(port))


IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def _network(value: object) -> IPNetwork:
    if isinstance(value, ipaddress.IPv4Network | ipaddress.IPv6Network):
        return value
    if isinstance(value, str):
        try:
            return ipaddress.ip_network(value.strip(), strict=False)
        except ValueError:
            pass
    raise _fail(f"must be an IPv4 or IPv6 network such as 10.0.0.0/8, not {_show(value)}")


def _network_text(value: IPNetwork) -> str:
    return str(value)


def _mqtt_url(value: str) -> str:
    parts = urlsplit(value)
    if parts.scheme not in ("mqtt", "mqtts"):
        raise _fail(f"must be mqtt://host[:port] or mqtts://host[:port], not {_show(value)}")
    if "@" in parts.netloc:
        raise _fail("must not hold credentials: use the username and password keys")
    try:
        port = parts.port
    except ValueError:
        raise _fail(f"port must be 0-65535, not {_show(value)}") from None
    if not parts.hostname:
        raise _fail(f"has no host: {_show(value)}")
    if parts.path not in ("", "/") or parts.query or parts.fragment or port == 0:
        raise _fail(f"must be {parts.scheme}://host[:port] and nothing more, not {_show(value)}")
    return value


def _mqtt_protocol(value: object) -> str:
    if isinstance(value, int | float) and not isinstance(value, bool) and value == 5:
        return "5"
    if isinstance(value, str) and value.strip() in ("3.1.1", "5", "5.0"):
        return "3.1.1" if value.strip() == "3.1.1" else "5"
    raise _fail(f'must be "3.1.1" or 5, not {_show(value)}')


def _base_topic(value: str) -> str:
    if not value:
        raise _fail("must not be empty")
    if any(c in value for c in "+#\0"):
        raise _fail(f"must not contain the MQTT wildcards + or #, not {_show(value)}")
    if value.startswith("/") or value.endswith("/"):
        raise _fail(f"must not start or end with /, not {_show(value)}")
    return value


def _existing_file(value: str) -> str:
    if not os.path.isfile(value):
        raise _fail(f"no such file: {value}")
    return value


Name = Annotated[str, AfterValidator(_name)]
NonEmpty = Annotated[str, AfterValidator(_not_empty)]
UnitId = Annotated[int, _between(*UNIT_ID_RANGE)]
PositiveInt = Annotated[int, AfterValidator(_positive)]
NonNegativeInt = Annotated[int, _at_least(0)]
NonNegative = Annotated[float, _at_least(0)]
SeriesField = Annotated[
    Series, PlainValidator(_series), PlainSerializer(_enum_name, when_used="json")
]
ProtocolField = Annotated[
    WireProtocol, PlainValidator(_protocol), PlainSerializer(_protocol_name, when_used="json")
]
Listen = Annotated[ListenAddress, PlainValidator(_listen), PlainSerializer(str, when_used="json")]
Network = Annotated[
    IPNetwork, PlainValidator(_network), PlainSerializer(_network_text, when_used="json")
]
ExistingFile = Annotated[str, AfterValidator(_existing_file)]


# ------------------------------------------------------------------------ the models

# Each field's ``description`` is its rule as the user reads it: docs/config-reference.md
# is generated from these (gateway/config_reference.py).  Where the default shown by
# pydantic would mislead (it depends on context), ``json_schema_extra`` says what to show.
_SHOWN_DEFAULT = "shown_default"
_SHOWN_TYPE = "shown_type"


def _span(bounds: tuple[int, int]) -> str:
    return f"{bounds[0]}-{bounds[1]}"


def _or_list(items: Iterable[str]) -> str:
    """``a, b, c or d``."""
    *rest, last = list(items)
    return f"{', '.join(rest)} or {last}" if rest else last


class _Model(BaseModel):
    model_config = ConfigDict(
        extra="forbid", frozen=True, allow_inf_nan=False, coerce_numbers_to_str=True
    )


class SensorConfig(_Model):
    """One sensor.  ``address`` and ``unit_id`` hold their final values once the sensor
    is part of a :class:`GatewayConfig` (a lone ``SensorConfig`` has ``unit_id`` 0)."""

    name: Name = Field(description=(
        "`[a-z0-9_-]+`, unique in the whole gateway: it is the sensor's name in MQTT "
        "topics and REST paths"))
    series: SeriesField = Field(description=(
        f"{_or_list(f'`{s.name}`' for s in Series)} (any case)"))
    address: int = Field(default=0, description=(
        f"the sensor's bus address: native {_span(ADDRESS_RANGE[WireProtocol.NATIVE])}, "
        f"modbus {_span(ADDRESS_RANGE[WireProtocol.MODBUS])}; unique on its bus"),
        json_schema_extra={_SHOWN_DEFAULT: "0 on a native bus, 1 on a modbus bus"})
    unit_id: UnitId = Field(default=0, description=(
        f"{_span(UNIT_ID_RANGE)}, unique; the Modbus TCP unit id of the sensor's register "
        "map. Sensors without one are numbered 1, 2, … in file order across all buses, "
        "skipping every `unit_id` and `raw_unit_id` given explicitly"),
        json_schema_extra={_SHOWN_DEFAULT: "1, 2, … in file order"})
    poll_hz: NonNegative = Field(default=10.0, description=(
        ">= 0; polls per second. 0: as fast as the bus allows, shared fairly with the "
        "other sensors"))
    stream_hz: NonNegative = Field(default=0.0, description=(
        ">= 0; > 0 turns on the sensor's own auto-output at that rate instead of polling. "
        f"Native: {_or_list(map(str, NATIVE_STREAM_HZ))}. Modbus: the interval "
        f"`round(1000 / stream_hz)` ms must be {_span(MODBUS_STREAM_INTERVAL_MS)} (about "
        "0.016-100 Hz). At most one streaming sensor per bus"))
    stale_after_ms: PositiveInt = Field(default=1000, description=(
        "> 0; a reading older than this is `stale`"))
    raw_unit_id: UnitId | None = Field(default=None, description=(
        f"{_span(UNIT_ID_RANGE)}; only for sensors on a modbus bus: a Modbus TCP unit id "
        "whose requests pass through to the sensor unchanged. Unique, and different from "
        "every `unit_id`"))


class BusConfig(_Model):
    """One serial line and the sensors on it; the bus master owns it alone."""

    name: Name = Field(description="`[a-z0-9_-]+`, unique among buses")
    port: Annotated[str, AfterValidator(_serial_port)] = Field(description=(
        "a device path (`/dev/ttyUSB0`, `/dev/serial/by-id/…`) or a pyserial URL: "
        "`socket://host:port`, `rfc2217://host:port`, `loop://` (also "
        f"{', '.join(f'`{s}://`' for s in PYSERIAL_SCHEMES[3:])}). Unique among buses"))
    baudrate: Annotated[int, AfterValidator(_baudrate)] = Field(default=9600, description=(
        f"{_or_list(map(str, BAUD_RATES))}: the rates the sensors have a code for. 9600 is "
        "the sensors' factory rate"))
    protocol: ProtocolField = Field(description="`native` or `modbus` (any case)")
    timeout_ms: PositiveInt | None = Field(default=None, description=(
        "> 0; how long to wait for an answer per attempt, on top of the wire time of the "
        "request and the answer, for every sensor of the bus. Leave it out: each "
        "sensor's timeout is then learned from its answers"),
        json_schema_extra={_SHOWN_DEFAULT: "null: learned per sensor (below)"})
    retries: Annotated[int, _between(0, 10)] = Field(default=1, description=(
        "0-10; attempts after the first before an exchange counts as failed"))
    trace: bool = Field(default=False, description=(
        "log one line per exchange on this bus (the bytes out and in, the time, the "
        "outcome), at most 50 a second; also `run --trace BUS`, and on every bus with "
        "`--log-level debug`"))
    rs485: bool = Field(default=False, description=(
        "put the port into the kernel's RS-485 mode (the driver switches the transmitter)"))
    sensors: Annotated[list[SensorConfig], Field(min_length=1)] = Field(description=(
        "the sensors on this line, at least one (`buses[].sensors[]`)"))

    @model_validator(mode="before")
    @classmethod
    def _default_addresses(cls, data: Any) -> Any:
        return _fill_bus_defaults(data)


class ModbusConfig(_Model):
    """The Modbus TCP server."""

    listen: Listen = Field(default=ListenAddress("0.0.0.0", 502), description=(
        "`host:port`, port 0-65535; an IPv6 host in brackets: `[::]:502`"))
    allow_writes: bool = Field(default=False, description=(
        "writes (FC06/FC16) are refused with exception 01 unless true"))
    allow_from: Annotated[list[Network], Field(min_length=1)] = Field(
        default_factory=lambda: [
            ipaddress.ip_network("0.0.0.0/0"), ipaddress.ip_network("::/0")
        ],
        description=(
            "at least one IPv4 or IPv6 network; host bits are allowed (`192.168.1.5/24` "
            "means `192.168.1.0/24`); a bare address is a single host. Clients from "
            "elsewhere are disconnected at once"),
    )
    max_connections: PositiveInt = Field(default=100, description=(
        "> 0; a client beyond this takes the place of the longest-idle connection, "
        "which is closed"))
    max_connections_per_address: PositiveInt = Field(default=20, description=(
        "> 0; a client address beyond this many connections takes the place of its own "
        "longest-idle one"))
    idle_timeout_s: NonNegative = Field(default=60.0, description=(
        ">= 0; a client connection idle this long is closed; 0: never"))

    def allows(self, client: str) -> bool:
        """Whether a client address (IPv4, IPv6, or IPv4-mapped IPv6) is in ``allow_from``."""
        try:
            ip = ipaddress.ip_address(client.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip in net for net in self.allow_from if net.version == ip.version)


class MqttConfig(_Model):
    """The MQTT client."""

    url: Annotated[str, AfterValidator(_mqtt_url)] = Field(
        default="mqtt://localhost:1883", description=(
            "`mqtt://host[:port]` (default port 1883) or `mqtts://host[:port]` for TLS "
            "(default 8883); no credentials, path or query in it"))
    username: NonEmpty | None = Field(default=None, description="not empty")
    password: str | None = Field(default=None, description=(
        "needs `username`; write `${VAR}` to take it from the environment"))
    ca_file: ExistingFile | None = Field(default=None, description=(
        "the CA that signed the broker's certificate; an existing file; needs `mqtts://`"),
        json_schema_extra={_SHOWN_DEFAULT: "null: the system's CAs"})
    certfile: ExistingFile | None = Field(default=None, description=(
        "client certificate; an existing file; needs `mqtts://`"))
    keyfile: ExistingFile | None = Field(default=None, description=(
        "client key; an existing file; needs `mqtts://` and `certfile`"))
    base_topic: Annotated[str, AfterValidator(_base_topic)] = Field(default="imu", description=(
        "first level of every topic; not empty, no `+` or `#`, no leading or trailing `/`"))
    qos: Annotated[int, _between(0, 2)] = Field(default=0, description=(
        "0-2; QoS of state and per-field messages"))
    retain: bool = Field(default=True, description="retain state and per-field messages")
    per_field_topics: bool = Field(default=False, description=(
        "also publish every value on its own topic (`{base}/{gateway_id}/{sensor}/{field}`)"))
    min_interval_ms: NonNegativeInt = Field(default=0, description=(
        ">= 0; at most one state message per sensor per interval (the latest is sent when "
        "it ends)"))
    homeassistant_discovery: bool = Field(default=False, description=(
        "publish Home Assistant discovery configs"))
    allow_commands: bool = Field(default=False, description=(
        "accept commands on `{base}/{gateway_id}/{sensor}/cmd/{command}`"))
    protocol: Annotated[Literal["3.1.1", "5"], PlainValidator(_mqtt_protocol)] = Field(
        default="3.1.1", description='`"3.1.1"` or `5` (MQTT 5)',
        json_schema_extra={_SHOWN_TYPE: "string or number", _SHOWN_DEFAULT: '`"3.1.1"`'})
    client_id: NonEmpty | None = Field(default=None, description="not empty", json_schema_extra={
        _SHOWN_DEFAULT: "null: `imu-gateway-{gateway_id}`"})
    #: a state message is sent only when a field moved by more than its deadband
    deadband: dict[str, Annotated[float, Field(ge=0, allow_inf_nan=False)]] = Field(
        default_factory=dict, description=(
            f"field (`{FIELD_NAMES[0]}` … `{FIELD_NAMES[-1]}`) or group "
            f"({', '.join(f'`{g.value}`' for g in Group)}) → band >= 0; a state message is sent "
            "only when a listed field moved more than its band ([mqtt.md](mqtt.md))"))
    #: messages kept while the broker is away; the oldest are dropped (and counted)
    queue_size: Annotated[int, Field(gt=0)] = Field(default=1000, description=(
        "> 0; messages kept while the broker is away, the oldest dropped first"))
    discovery_prefix: Annotated[str, AfterValidator(_base_topic)] = Field(
        default="homeassistant", description=(
            "Home Assistant's discovery prefix; rules as for `base_topic`"))

    @field_validator("deadband")
    @classmethod
    def _deadband_fields(cls, value: dict[str, float]) -> dict[str, float]:
        known = {*FIELD_NAMES, *(g.value for g in Group)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise _fail(f"unknown field {', '.join(map(_show, unknown))} (fields: "
                        f"{' '.join(FIELD_NAMES)}; or a group: {' '.join(g.value for g in Group)})")
        return value

    def field_deadbands(self) -> dict[str, float]:
        """The deadband of each field, a group's applied to its members (a field's own
        value wins)."""
        out: dict[str, float] = {}
        for group, (_, names) in GROUP_FIELDS.items():
            if group.value in self.deadband:
                out.update(dict.fromkeys(names, self.deadband[group.value]))
        out.update({k: v for k, v in self.deadband.items() if k in FIELD_NAMES})
        return out

    @field_validator("password")
    @classmethod
    def _password_needs_username(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is not None and info.data.get("username", "") is None:
            raise _fail("needs a username")
        return value

    @field_validator("ca_file", "certfile", "keyfile")
    @classmethod
    def _tls_only(cls, value: str | None, info: ValidationInfo) -> str | None:
        url = info.data.get("url")
        if value is not None and url is not None and not url.startswith("mqtts://"):
            raise _fail("needs an mqtts:// url (TLS)")
        if info.field_name == "keyfile" and value is not None and \
                info.data.get("certfile", "") is None:
            raise _fail("needs a certfile")
        return value

    @property
    def tls(self) -> bool:
        return self.url.startswith("mqtts://")

    @property
    def host(self) -> str:
        return urlsplit(self.url).hostname or "localhost"

    @property
    def port(self) -> int:
        return urlsplit(self.url).port or (8883 if self.tls else 1883)


class HttpConfig(_Model):
    """The REST API and dashboard."""

    listen: Listen = Field(default=ListenAddress("0.0.0.0", 8080), description=(
        "`host:port` as for `modbus.listen`"))
    token: NonEmpty | None = Field(default=None, description=(
        "not empty; the bearer token (`Authorization: Bearer …`); write `${VAR}` to take "
        "it from the environment"))
    allow_commands: bool = Field(default=False, description=(
        "accept `POST /api/v1/sensors/{name}/commands/{command}`; needs `token`"))
    read_token_required: bool = Field(default=False, description=(
        "reads need the token too; needs `token`"))

    @field_validator("allow_commands", "read_token_required")
    @classmethod
    def _needs_token(cls, value: bool, info: ValidationInfo) -> bool:
        if value and info.data.get("token", "") is None:
            raise _fail("needs http.token (the bearer token clients must send)")
        return value


class GatewayConfig(_Model):
    """The whole file.  A section left out (``None``) is an interface turned off."""

    gateway_id: Annotated[str, AfterValidator(_gateway_id)] = Field(
        default_factory=socket.gethostname,
        description="`[A-Za-z0-9_.-]+`; part of every MQTT topic",
        json_schema_extra={_SHOWN_DEFAULT: "the host name"},
    )
    buses: Annotated[list[BusConfig], Field(min_length=1)] = Field(description=(
        "the serial lines, at least one (`buses[]`)"))
    modbus: ModbusConfig | None = Field(default=None, description=(
        "the Modbus TCP server (`modbus`); left out: off"))
    mqtt: MqttConfig | None = Field(default=None, description=(
        "the MQTT client (`mqtt`); left out: off"))
    http: HttpConfig | None = Field(default=None, description=(
        "the REST API and dashboard (`http`); left out: off"))

    @model_validator(mode="before")
    @classmethod
    def _context_defaults(cls, data: Any) -> Any:
        return _fill_defaults(data)

    @model_validator(mode="after")
    def _cross_check(self) -> Self:
        # Not a ValueError on purpose: it carries several problems, each with its path.
        problems = _cross_problems(_views(self))
        if problems:
            raise ConfigError(problems)
        return self

    def iter_sensors(self) -> Iterator[tuple[BusConfig, SensorConfig]]:
        """Every sensor with its bus, in file order."""
        for bus in self.buses:
            for sensor in bus.sensors:
                yield bus, sensor

    def interfaces(self) -> list[str]:
        """The interfaces turned on: ``modbus``, ``mqtt``, ``http``, in that order."""
        return [n for n in ("modbus", "mqtt", "http") if getattr(self, n) is not None]

    def summary(self) -> str:
        """``gateway lab-1, 2 buses, 3 sensors; interfaces: modbus, http``."""
        buses = len(self.buses)
        sensors = sum(len(bus.sensors) for bus in self.buses)
        return (
            f"gateway {self.gateway_id}, {buses} bus{'es' if buses != 1 else ''}, "
            f"{sensors} sensor{'s' if sensors != 1 else ''}; "
            f"interfaces: {', '.join(self.interfaces()) or 'none'}"
        )


# ------------------------------------------------------------ defaults from context


def _plain(item: Any) -> Any:
    """A model instance as the dict of what was given, so its defaults are filled again."""
    if isinstance(item, BaseModel):
        return item.model_dump(exclude_unset=True)
    if isinstance(item, Mapping):
        return dict(item)
    return item


def _protocol_or_none(value: object) -> WireProtocol | None:
    try:
        return _protocol(value)
    except PydanticCustomError:
        return None


def _int_or_none(value: object) -> int | None:
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip().isdigit():
        return int(value)
    return None


def _fill_bus_defaults(data: Any) -> Any:
    """A bus mapping with each sensor's missing ``address`` set from the bus protocol."""
    if not isinstance(data, Mapping):
        return data
    bus = dict(data)
    protocol = _protocol_or_none(bus.get("protocol"))
    sensors = bus.get("sensors")
    if isinstance(sensors, list | tuple):
        filled = []
        for item in sensors:
            sensor = _plain(item)
            if isinstance(sensor, dict) and sensor.get("address") is None and protocol is not None:
                sensor["address"] = DEFAULT_ADDRESS[protocol]
            filled.append(sensor)
        bus["sensors"] = filled
    return bus


def _fill_defaults(data: Any) -> Any:
    """The gateway mapping with addresses and unit ids filled in where not given."""
    if not isinstance(data, Mapping) or not isinstance(data.get("buses"), list | tuple):
        return data
    buses = [_fill_bus_defaults(_plain(bus)) for bus in data["buses"]]
    sensors = [
        sensor
        for bus in buses if isinstance(bus, dict) and isinstance(bus.get("sensors"), list)
        for sensor in bus["sensors"] if isinstance(sensor, dict)
    ]
    taken = {
        n for sensor in sensors for key in ("unit_id", "raw_unit_id")
        if (n := _int_or_none(sensor.get(key))) is not None
    }
    next_id = 1
    for sensor in sensors:
        if sensor.get("unit_id") is None:
            while next_id in taken:
                next_id += 1
            sensor["unit_id"] = next_id
            taken.add(next_id)
    return {**data, "buses": buses}


# --------------------------------------------------------------- cross-field checks


@dataclass(frozen=True, slots=True)
class _SensorView:
    """A sensor for the cross-field checks: each value ``None`` when absent or invalid."""

    path: str
    name: str | None
    address: int | None
    unit_id: int | None
    raw_unit_id: int | None
    stream_hz: float | None


@dataclass(frozen=True, slots=True)
class _BusView:
    path: str
    name: str | None
    port: str | None
    protocol: WireProtocol | None
    sensors: list[_SensorView]


def _views(config: GatewayConfig) -> list[_BusView]:
    return [
        _BusView(f"buses[{i}]", bus.name, bus.port, bus.protocol, [
            _SensorView(f"buses[{i}].sensors[{j}]", s.name, s.address, s.unit_id,
                        s.raw_unit_id, s.stream_hz)
            for j, s in enumerate(bus.sensors)
        ])
        for i, bus in enumerate(config.buses)
    ]


_ADAPTERS: dict[tuple[type[BaseModel], str], TypeAdapter[Any]] = {}


def _field_or_none(model: type[BaseModel], key: str, data: Mapping[str, Any]) -> Any:
    """One field of ``model`` validated on its own: its default when absent, ``None``
    when invalid (the field's own problem is reported by pydantic)."""
    field = model.model_fields[key]
    if key not in data:
        return field.get_default(call_default_factory=True)
    adapter = _ADAPTERS.get((model, key))
    if adapter is None:
        annotated: Any = field.annotation
        if field.metadata:
            annotated = cast(Any, Annotated)[(annotated, *field.metadata)]
        adapter = _ADAPTERS[(model, key)] = TypeAdapter(annotated, config=_Model.model_config)
    try:
        return adapter.validate_python(data[key])
    except ValidationError:
        return None


def _salvage(data: Any) -> list[_BusView]:
    """What is valid of a config that failed validation, value by value, so that the
    cross-field checks still run on it."""
    data = _fill_defaults(data)
    if not isinstance(data, Mapping) or not isinstance(data.get("buses"), list):
        return []
    views = []
    for i, bus in enumerate(data["buses"]):
        if not isinstance(bus, Mapping):
            continue
        raw_sensors = bus.get("sensors")
        sensors = [
            _SensorView(
                f"buses[{i}].sensors[{j}]",
                _field_or_none(SensorConfig, "name", raw),
                _field_or_none(SensorConfig, "address", raw),
                _field_or_none(SensorConfig, "unit_id", raw),
                _field_or_none(SensorConfig, "raw_unit_id", raw),
                _field_or_none(SensorConfig, "stream_hz", raw),
            )
            for j, raw in enumerate(raw_sensors if isinstance(raw_sensors, list) else [])
            if isinstance(raw, Mapping)
        ]
        views.append(_BusView(
            f"buses[{i}]",
            _field_or_none(BusConfig, "name", bus),
            _field_or_none(BusConfig, "port", bus),
            _field_or_none(BusConfig, "protocol", bus),
            sensors,
        ))
    return views


def _stream_problem(protocol: WireProtocol, hz: float) -> str | None:
    if hz == 0:
        return None
    if protocol is WireProtocol.NATIVE:
        if hz not in NATIVE_STREAM_HZ:
            rates = ", ".join(map(str, NATIVE_STREAM_HZ))
            return f"must be 0 or one of {rates} on a native bus, not {_number(hz)}"
        return None
    low, high = MODBUS_STREAM_INTERVAL_MS
    if not low <= round(1000 / hz) <= high:
        return (
            f"on a modbus bus the output interval round(1000/stream_hz) must be "
            f"{low}-{high} ms (stream_hz about 0.016-100), not {_number(hz)}"
        )
    return None


def _cross_problems(buses: list[_BusView]) -> list[str]:
    """Every problem that spans fields: uniqueness, per-protocol ranges, streaming."""
    problems: list[str] = []

    def claim(seen: dict[Any, str], key: Any, owner: str, at: str, shown: str) -> None:
        if key in seen:
            problems.append(f"{at}: {shown} is already used by {seen[key]}")
        else:
            seen[key] = owner

    bus_names: dict[str, str] = {}
    ports: dict[str, str] = {}
    sensor_names: dict[str, str] = {}
    unit_ids: dict[int, str] = {}
    for bus in buses:
        if bus.name is not None:
            claim(bus_names, bus.name, bus.path, f"{bus.path}.name", _show(bus.name))
        if bus.port is not None:
            claim(ports, bus.port, bus.path, f"{bus.path}.port", _show(bus.port))
        addresses: dict[int, str] = {}
        streaming: str | None = None
        for sensor in bus.sensors:
            path = sensor.path
            if sensor.name is not None:
                claim(sensor_names, sensor.name, path, f"{path}.name", _show(sensor.name))
            for key in ("unit_id", "raw_unit_id"):
                unit_id = getattr(sensor, key)
                if unit_id is not None:
                    claim(unit_ids, unit_id, f"{path}.{key}", f"{path}.{key}",
                          f"unit id {unit_id}")
            if bus.protocol is not None:
                kind = _protocol_name(bus.protocol)
                low, high = ADDRESS_RANGE[bus.protocol]
                if sensor.address is None:
                    pass
                elif not low <= sensor.address <= high:
                    problems.append(f"{path}.address: must be {low}-{high} on a {kind} bus, "
                                    f"not {sensor.address}")
                else:
                    claim(addresses, sensor.address, path, f"{path}.address",
                          f"address {sensor.address}")
                stream = None if sensor.stream_hz is None else \
                    _stream_problem(bus.protocol, sensor.stream_hz)
                if stream:
                    problems.append(f"{path}.stream_hz: {stream}")
                if sensor.raw_unit_id is not None and bus.protocol is not WireProtocol.MODBUS:
                    problems.append(f"{path}.raw_unit_id: only for sensors on a modbus bus; "
                                    f"{bus.path} is {kind}")
            if sensor.stream_hz:
                if streaming is not None:
                    problems.append(f"{path}.stream_hz: only one sensor per bus may stream; "
                                    f"{streaming} already does")
                else:
                    streaming = path
    return problems


# --------------------------------------------------- pydantic errors, in one place


def _model_in(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in get_args(annotation):
        found = _model_in(arg)
        if found is not None:
            return found
    return None


def _unknown_key(loc: tuple[int | str, ...]) -> str:
    model: type[BaseModel] = GatewayConfig
    for part in loc[:-1]:
        if isinstance(part, str):
            field = model.model_fields.get(part)
            inner = _model_in(field.annotation) if field else None
            if inner is None:
                break
            model = inner
    allowed = list(model.model_fields)
    close = difflib.get_close_matches(str(loc[-1]), allowed, n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    return f"unknown key (allowed: {', '.join(allowed)}){hint}"


_TYPE_MESSAGES: Mapping[str, str] = {
    "int_type": "must be a whole number",
    "int_parsing": "must be a whole number",
    "int_from_float": "must be a whole number",
    "float_type": "must be a number",
    "float_parsing": "must be a number",
    "finite_number": "must be a finite number",
    "bool_type": "must be true or false",
    "bool_parsing": "must be true or false",
    "string_type": "must be a string",
    "list_type": "must be a list",
    "model_type": "must be a mapping (key: value)",
    "model_attributes_type": "must be a mapping (key: value)",
    "dict_type": "must be a mapping (key: value)",
}


def _pydantic_problem(error: ErrorDetails) -> str:
    """One pydantic error as ``<yaml path>: <message>``."""
    loc = error["loc"]
    kind = error["type"]
    value = error.get("input")
    if kind == "config":
        message = error["msg"]
    elif kind == "missing":
        message = "required"
    elif kind == "extra_forbidden":
        message = _unknown_key(loc)
    elif kind == "too_short":
        message = "must not be empty"
    elif kind in _TYPE_MESSAGES:
        message = _TYPE_MESSAGES[kind]
        if kind == "string_type" and isinstance(value, bool):
            message += " (put it in quotes)"
        if not (loc and loc[-1] in _SECRET_KEYS):
            message += f", not {_show(value)}"
    else:
        message = error["msg"].removeprefix("Value error, ")
        message = message[:1].lower() + message[1:]
    return f"{_path(loc) or '(top level)'}: {message}"


# ------------------------------------------------------------------------- loading


def _expand_env(
    node: Any, loc: tuple[int | str, ...], env: Mapping[str, str],
    problems: list[str], unresolved: set[str],
) -> Any:
    """``${NAME}`` in every string value replaced from ``env``; ``$${`` is a literal ``${``."""
    if isinstance(node, dict):
        return {k: _expand_env(v, (*loc, str(k)), env, problems, unresolved)
                for k, v in node.items()}
    if isinstance(node, list):
        return [_expand_env(v, (*loc, i), env, problems, unresolved)
                for i, v in enumerate(node)]
    if not isinstance(node, str) or "${" not in node:
        return node
    path = _path(loc)
    out: list[str] = []
    pos = 0
    ok = True
    for match in _ENV_REF.finditer(node):
        out.append(node[pos:match.start()])
        pos = match.end()
        name = match.group(1)
        if match.group(0) == "$${":
            out.append("${")
        elif name is None:
            problems.append(f"{path}: unterminated ${{ (write $${{ for a literal ${{)")
            ok = False
        elif not _ENV_NAME.fullmatch(name):
            problems.append(f"{path}: {_show('${' + name + '}')} is not an environment "
                            "variable reference (a name is letters, digits and _)")
            ok = False
        elif name not in env:
            problems.append(f"{path}: environment variable {name} is not set")
            ok = False
        else:
            out.append(env[name])
    out.append(node[pos:])
    if not ok:
        unresolved.add(path)
        return node
    return "".join(out)


def config_from_dict(
    data: Mapping[str, Any], env: Mapping[str, str] | None = None
) -> GatewayConfig:
    """Validate already-parsed config data (``${NAME}`` expanded from ``env``,
    default ``os.environ``).  Raises :class:`ConfigError` with every problem."""
    problems: list[str] = []
    unresolved: set[str] = set()
    expanded = _expand_env(dict(data), (), os.environ if env is None else env,
                           problems, unresolved)
    try:
        config = GatewayConfig.model_validate(expanded)
    except ValidationError as exc:
        for error in exc.errors():
            if _path(error["loc"]) not in unresolved:
                problems.append(_pydantic_problem(error))
        # Best effort on a config already known to be bad: never let it hide those problems.
        with contextlib.suppress(Exception):
            problems += _cross_problems(_salvage(expanded))
    except ConfigError as exc:
        problems += exc.problems
    else:
        if not problems:
            return config
    raise ConfigError(problems)


class _Loader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping (PyYAML keeps the last)."""


def _construct_mapping(loader: _Loader, node: yaml.MappingNode) -> dict[Any, Any]:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node)
        try:
            first = seen.setdefault(key, key_node.start_mark.line)
        except TypeError:  # an unhashable key: SafeLoader reports it
            continue
        if first != key_node.start_mark.line:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {_show(key)} (first given on line {first + 1})",
                key_node.start_mark,
            )
    return loader.construct_mapping(node)


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _kind(value: object) -> str:
    if isinstance(value, list):
        return "a list"
    if isinstance(value, bool):
        return "true/false"
    if isinstance(value, str):
        return "a string"
    return "a number" if isinstance(value, int | float) else f"a {type(value).__name__}"


def load_config_text(
    text: str, source: str = "<config>", env: Mapping[str, str] | None = None
) -> GatewayConfig:
    """Parse and validate YAML text; ``source`` names it in file-level problems."""
    try:
        data = yaml.load(text, Loader=_Loader)  # a SafeLoader subclass
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark else source
        what = " ".join(str(exc.problem or exc.context or "syntax error").split())
        raise ConfigError([f"{where}: invalid YAML: {what}"]) from None
    except yaml.YAMLError as exc:
        raise ConfigError([f"{source}: invalid YAML: {' '.join(str(exc).split())}"]) from None
    if data is None:
        raise ConfigError([f"{source}: empty file: expected a mapping with at least 'buses'"])
    if not isinstance(data, dict):
        raise ConfigError(
            [f"{source}: the top level must be a mapping (key: value), not {_kind(data)}"]
        )
    return config_from_dict(data, env)


def load_config(path: str | os.PathLike[str], env: Mapping[str, str] | None = None
                ) -> GatewayConfig:
    """Read, parse and validate a config file.  Raises :class:`ConfigError`, never
    anything else for a bad or missing file."""
    source = os.fspath(path)
    reasons: dict[type[OSError], str] = {
        FileNotFoundError: "no such file",
        IsADirectoryError: "is a directory, not a config file",
        PermissionError: "cannot read: permission denied",
    }
    try:
        raw = Path(source).read_bytes()
    except OSError as exc:
        reason = reasons.get(type(exc)) or f"cannot read: {exc.strerror or exc}"
        raise ConfigError([f"{source}: {reason}"]) from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError([f"{source}: not UTF-8 text (bad byte at offset {exc.start})"]) \
            from None
    return load_config_text(text, source, env)

