"""The config's sections as pydantic models, and the defaults they take from their
context (a bus's protocol gives its sensors' timeouts)."""

from __future__ import annotations

import ipaddress
import re
import socket
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Self
from urllib.parse import urlsplit

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    ValidationInfo,
    field_validator,
    model_validator,
)

from .. import passwords
from ..alarms import COMMUNICATION, AlarmRow, Severity
from ..errors import ConfigError
from ..model import VALUE_GROUPS, Group, Series, WireProtocol
from ..normalise import FIELD_NAMES, MEASURED_FIELDS
from .checks import BusView, SensorView, cross_problems
from .fields import (
    ADDRESS_RANGE,
    BAUD_RATES,
    DEFAULT_ADDRESS,
    MODBUS_STREAM_INTERVAL_MS,
    NATIVE_STREAM_HZ,
    PYSERIAL_SCHEMES,
    UNIT_ID_RANGE,
    BaudRate,
    ExistingFile,
    FileToKeep,
    GatewayId,
    Listen,
    ListenAddress,
    MqttProtocol,
    MqttUrls,
    Name,
    Network,
    NonEmpty,
    NonNegative,
    NonNegativeInt,
    PositiveInt,
    ProtocolField,
    SerialPort,
    SeriesField,
    SparkplugId,
    TopicPrefix,
    UnitId,
    between,
    fail,
    protocol_or_none,
    show,
    show_number,
)

# ------------------------------------------------------------------------ the models

# Each field's ``description`` is its rule as the user reads it: docs/config-reference.md
# is generated from these (imu_gateway/config_reference.py).  Where the default shown by
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


def _alarm_name(value: str) -> str:
    if not re.fullmatch(r"[a-z0-9_]+", value):
        raise fail(f"must match [a-z0-9_]+ (lower-case letters, digits and _: it is a "
                    f"topic level and a metric name), not {show(value)}")
    if value == COMMUNICATION:
        raise fail(f"{COMMUNICATION} is the built-in alarm of every sensor (stale or "
                    "offline); give this one another name")
    return value


def _severity(value: object) -> Severity:
    if isinstance(value, Severity):
        return value
    if isinstance(value, str) and value.strip().lower() in {s.value for s in Severity}:
        return Severity(value.strip().lower())
    raise fail(f"must be one of {', '.join(s.value for s in Severity)}, not {show(value)}")


AlarmName = Annotated[str, AfterValidator(_alarm_name)]
SeverityField = Annotated[Severity, PlainValidator(_severity),
                          PlainSerializer(lambda s: s.value, when_used="json")]


class AlarmConfig(_Model):
    """One alarm of a sensor (docs/alarms.md): a field beyond a limit."""

    name: AlarmName = Field(description=(
        f"`[a-z0-9_]+`, unique per sensor, not `{COMMUNICATION}` (every sensor's built-in "
        "alarm)"))
    field: NonEmpty = Field(description=(
        "a field the sensor's series measures (`pitch`, `accel_z`, …; the derived ones "
        "too, where the series has them)"))
    above: float | None = Field(default=None, description=(
        "active while the value is above this (strictly)"))
    below: float | None = Field(default=None, description=(
        "active while the value is below this (strictly); with `above` too: active "
        "outside the band, and `below` < `above`. One of the two is required"))
    hysteresis: NonNegative = Field(default=0.0, description=(
        ">= 0; an active alarm clears only at `above - hysteresis` or lower (at "
        "`below + hysteresis` or higher)"))
    on_delay_s: NonNegative = Field(default=0.0, description=(
        ">= 0; the value must stay beyond the limit this long before the alarm is active"))
    off_delay_s: NonNegative = Field(default=0.0, description=(
        ">= 0; the value must stay back within the limit this long before it clears"))
    severity: SeverityField = Field(default=Severity.WARNING, description=(
        f"{_or_list(f'`{s.value}`' for s in Severity)}"),
        json_schema_extra={_SHOWN_DEFAULT: "`warning`", _SHOWN_TYPE: "string"})
    latch: bool = Field(default=False, description=(
        "true: once active, it stays active until acknowledged, even when the value "
        "returns"))

    @model_validator(mode="after")
    def _limits(self) -> Self:
        if self.above is None and self.below is None:
            raise fail("needs above, below or both (a band): the limit it raises at")
        if self.above is not None and self.below is not None:
            if self.below >= self.above:
                raise fail(f"below ({show_number(self.below)}) must be less than above "
                            f"({show_number(self.above)}): the alarm is active outside "
                            "the band between them")
            if self.below + self.hysteresis >= self.above - self.hysteresis:
                raise fail(f"hysteresis {show_number(self.hysteresis)} closes the band "
                            f"{show_number(self.below)}..{show_number(self.above)}: an "
                            "active alarm could never clear; make it smaller than half "
                            "the band")
        return self

    def row(self, sensor: str) -> AlarmRow:
        """The alarm as ``imu_gateway.alarms`` evaluates it."""
        return AlarmRow(sensor, self.name, self.field, self.above, self.below,
                        self.hysteresis, self.on_delay_s, self.off_delay_s, self.severity,
                        self.latch)


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
    # (a tuple: a sensor's config stays hashable)
    alarms: tuple[AlarmConfig, ...] = Field(default=(), description=(
        "the sensor's alarms (`buses[].sensors[].alarms[]`, [alarms.md](alarms.md)); the "
        f"built-in `{COMMUNICATION}` alarm is there without a row"),
        json_schema_extra={_SHOWN_DEFAULT: "`[]`"})

    @model_validator(mode="after")
    def _alarms_fit(self) -> Self:
        measured = MEASURED_FIELDS[self.series]
        seen: dict[str, int] = {}
        for i, alarm in enumerate(self.alarms):
            if alarm.name in seen:
                raise fail(f"alarms[{i}].name: {show(alarm.name)} is already used by "
                            f"alarms[{seen[alarm.name]}]")
            seen[alarm.name] = i
            if alarm.field not in measured:
                raise fail(f"alarms[{i}].field: series {self.series.name} does not measure "
                            f"{show(alarm.field)} (its fields: {' '.join(measured)})")
        return self


class BusConfig(_Model):
    """One serial line and the sensors on it; the bus master owns it alone."""

    name: Name = Field(description="`[a-z0-9_-]+`, unique among buses")
    port: SerialPort = Field(description=(
        "a device path (`/dev/ttyUSB0`, `/dev/serial/by-id/…`) or a pyserial URL: "
        "`socket://host:port`, `rfc2217://host:port`, `loop://` (also "
        f"{', '.join(f'`{s}://`' for s in PYSERIAL_SCHEMES[3:])}). Unique among buses"))
    baudrate: BaudRate = Field(default=9600, description=(
        f"{_or_list(map(str, BAUD_RATES))}: the rates the sensors have a code for. 9600 is "
        "the sensors' factory rate"))
    protocol: ProtocolField = Field(description="`native` or `modbus` (any case)")
    timeout_ms: PositiveInt | None = Field(default=None, description=(
        "> 0; how long to wait for an answer per attempt, on top of the wire time of the "
        "request and the answer, for every sensor of the bus. Leave it out: each "
        "sensor's timeout is then learned from its answers"),
        json_schema_extra={_SHOWN_DEFAULT: "null: learned per sensor (below)"})
    retries: Annotated[int, between(0, 10)] = Field(default=1, description=(
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


#: What a Modbus/TCP Security role may do (docs/modbus-tcp.md has each function code's right).
ModbusRight = Literal["read", "write", "passthrough"]
_DEFAULT_ROLES: dict[str, list[ModbusRight]] = {
    "Viewer": ["read"], "Operator": ["read", "write"],
    "Engineer": ["read", "write", "passthrough"]}


class ModbusTlsConfig(_Model):
    """Modbus/TCP Security: mutual TLS on its own port, each client's rights taken from
    the role in its certificate (docs/modbus-tcp.md)."""

    listen: Listen = Field(default=ListenAddress("0.0.0.0", 802), description=(
        "`host:port` as for `modbus.listen`; 802 is Modbus/TCP Security's port"))
    certfile: ExistingFile = Field(description=(
        "the gateway's certificate (PEM), the CA's chain after it if there is one; an "
        "existing file"))
    keyfile: ExistingFile = Field(description=(
        "its private key (PEM, unencrypted); an existing file"))
    ca_file: ExistingFile = Field(description=(
        "the CA (PEM) whose client certificates are accepted; a client without a "
        "certificate it signed is refused at the handshake; an existing file"))
    roles: dict[NonEmpty, list[ModbusRight]] = Field(
        default_factory=lambda: dict(_DEFAULT_ROLES),
        description=(
            "role → rights (`read`, `write`, `passthrough`): what a client whose certificate "
            "carries that role (extension 1.3.6.1.4.1.50316.802.1) may do; names are "
            "case-sensitive"),
        json_schema_extra={_SHOWN_DEFAULT: (
            "`{Viewer: [read], Operator: [read, write], Engineer: [read, write, "
            "passthrough]}`")})
    default_role: NonEmpty | None = Field(default=None, description=(
        "a role of `roles` whose rights a certificate without a role, or with a role not "
        "in `roles`, gets; null: none, every request of such a client is refused with "
        "exception 01"))

    @model_validator(mode="after")
    def _default_role_is_a_role(self) -> Self:
        if self.default_role is not None and self.default_role not in self.roles:
            raise fail(f"default_role: {show(self.default_role)} is not in roles "
                        f"({', '.join(self.roles) or 'none'}); name one of them, or null")
        return self


class ModbusConfig(_Model):
    """The Modbus TCP server."""

    listen: Listen | None = Field(default=ListenAddress("0.0.0.0", 502), description=(
        "`host:port`, port 0-65535; an IPv6 host in brackets: `[::]:502`. null: no plain "
        "port (needs `tls`), only Modbus/TCP Security serves"))
    allow_writes: bool = Field(default=False, description=(
        "writes (FC06/FC16) on the plain port are refused with exception 01 unless true; "
        "on the TLS port the role's rights decide"))
    allow_from: Annotated[list[Network], Field(min_length=1)] = Field(
        default_factory=lambda: [
            ipaddress.ip_network("0.0.0.0/0"), ipaddress.ip_network("::/0")
        ],
        description=(
            "at least one IPv4 or IPv6 network; host bits are allowed (`192.168.1.5/24` "
            "means `192.168.1.0/24`); a bare address is a single host. Clients from "
            "elsewhere are disconnected at once (on both ports)"),
    )
    max_connections: PositiveInt = Field(default=100, description=(
        "> 0; a client beyond this takes the place of the longest-idle connection, "
        "which is closed"))
    max_connections_per_address: PositiveInt = Field(default=20, description=(
        "> 0; a client address beyond this many connections takes the place of its own "
        "longest-idle one"))
    idle_timeout_s: NonNegative = Field(default=60.0, description=(
        ">= 0; a client connection idle this long is closed; 0: never"))
    tls: ModbusTlsConfig | None = Field(default=None, description=(
        "Modbus/TCP Security (`modbus.tls`), beside the plain port; null: off"))

    @model_validator(mode="after")
    def _serves_somewhere(self) -> Self:
        if self.listen is None and self.tls is None:
            raise fail("listen: null turns the plain port off, and there is no tls "
                        "section: nothing would serve; give a listen address, add "
                        "modbus.tls, or leave the modbus section out")
        return self

    def allows(self, client: str) -> bool:
        """Whether a client address (IPv4, IPv6, or IPv4-mapped IPv6) is in ``allow_from``."""
        try:
            ip = ipaddress.ip_address(client.split("%", 1)[0])
        except ValueError:
            return False
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        return any(ip in net for net in self.allow_from if net.version == ip.version)


@dataclass(frozen=True, slots=True)
class Broker:
    """One broker of ``mqtt.url``."""

    host: str
    port: int

    @classmethod
    def of(cls, url: str) -> Broker:
        parts = urlsplit(url)
        return cls(parts.hostname or "localhost",
                   parts.port or (8883 if parts.scheme == "mqtts" else 1883))

    def __str__(self) -> str:
        return f"{self.host}:{self.port}"


class SparkplugConfig(_Model):
    """Sparkplug B on the brokers of ``mqtt.url``: the gateway an edge node, each sensor
    a device (docs/sparkplug.md)."""

    group_id: SparkplugId = Field(description=(
        "the Sparkplug group id; not empty, no `/`, `+` or `#`"))
    plain_topics: bool = Field(default=True, description=(
        "keep the plain topics (`{base}/{gateway_id}/…`) too; false: Sparkplug only"))
    allow_commands: bool = Field(default=False, description=(
        "run the catalogue's commands written as DCMD metrics (`Commands/…`)"))
    primary_host_id: SparkplugId | None = Field(
        default=None, description=(
            "the primary host application whose `spBv1.0/STATE/{id}` must say online "
            "before the gateway is born; null: none is waited for"))
    client_id: NonEmpty | None = Field(default=None, description="not empty", json_schema_extra={
        _SHOWN_DEFAULT: "null: `imu-gateway-{gateway_id}-sparkplug`"})
    bdseq_file: FileToKeep | None = Field(default=None, description=(
        "where the birth/death sequence number is kept across restarts (its folder must "
        "exist); null: it starts at 0 with each start"))


class MqttConfig(_Model):
    """The MQTT client."""

    url: MqttUrls = Field(
        default="mqtt://localhost:1883", description=(
            "`mqtt://host[:port]` (default port 1883) or `mqtts://host[:port]` for TLS "
            "(default 8883); no credentials, path or query in it. Or a list of them, the "
            "nodes of a cluster, one scheme for all: the gateway moves to the next when "
            "one is lost"))
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
    base_topic: TopicPrefix = Field(default="imu", description=(
        "first level of every topic; not empty, no `+` or `#`, no leading or trailing `/`"))
    qos: Annotated[int, between(0, 2)] = Field(default=0, description=(
        "0-2; QoS of state and per-field messages"))
    retain: bool = Field(default=True, description="retain state and per-field messages")
    per_field_topics: bool = Field(default=False, description=(
        "also publish every value on its own topic (`{base}/{gateway_id}/{sensor}/{field}`)"))
    min_interval_ms: NonNegativeInt = Field(default=0, description=(
        ">= 0; at most one state message per sensor per interval (the latest is sent when "
        "it ends)"))
    homeassistant_discovery: bool = Field(default=False, description=(
        "publish Home Assistant discovery configs"))
    homeassistant_min_interval_ms: NonNegativeInt = Field(default=1000, description=(
        ">= 0; with discovery, at most one state per sensor per interval for Home "
        "Assistant's entities (their own topic, `…/{sensor}/ha`); a status change goes at "
        "once"))
    homeassistant_url: str | None = Field(default=None, description=(
        "the dashboard's address in Home Assistant's device page (`configuration_url`)"),
        json_schema_extra={_SHOWN_DEFAULT: "null: from `http.listen` and the host name"})
    allow_commands: bool = Field(default=False, description=(
        "accept commands on `{base}/{gateway_id}/{sensor}/cmd/{command}`"))
    protocol: MqttProtocol = Field(
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
    #: messages waiting for the broker; with backfill, the states kept while it is away
    queue_size: Annotated[int, Field(gt=0)] = Field(default=1000, description=(
        "> 0; messages waiting to be sent, and with `backfill` the states kept while the "
        "broker is away; the oldest dropped first (and counted)"))
    backfill: bool = Field(default=False, description=(
        "send the states missed while the broker was away, after the reconnect, on "
        "`{base}/{gateway_id}/{sensor}/history` with their own `ts` (never on the state "
        "topic, which gets the latest once); off: they are dropped and counted"))
    backfill_per_s: Annotated[float, Field(gt=0, allow_inf_nan=False)] = Field(
        default=50.0, description="> 0; the most backfilled messages sent a second")
    state_expiry_s: Annotated[int, Field(gt=0)] | None = Field(default=None, description=(
        "> 0; MQTT 5: the message expiry of state and per-field messages, so that a broker "
        "stops serving a retained state this old; null: none"))
    discovery_prefix: TopicPrefix = Field(
        default="homeassistant", description=(
            "Home Assistant's discovery prefix; rules as for `base_topic`"))
    sparkplug: SparkplugConfig | None = Field(default=None, description=(
        "Sparkplug B ([sparkplug.md](sparkplug.md)); null: off"))

    @field_validator("deadband")
    @classmethod
    def _deadband_fields(cls, value: dict[str, float]) -> dict[str, float]:
        known = {*FIELD_NAMES, *(g.value for g in Group)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise fail(f"unknown field {', '.join(map(show, unknown))} (fields: "
                        f"{' '.join(FIELD_NAMES)}; or a group: {' '.join(g.value for g in Group)})")
        return value

    def field_deadbands(self) -> dict[str, float]:
        """The deadband of each field, a group's applied to its members (a field's own
        value wins)."""
        out: dict[str, float] = {}
        for group, spec in VALUE_GROUPS.items():
            if group.value in self.deadband:
                out.update(dict.fromkeys(spec.fields, self.deadband[group.value]))
        out.update({k: v for k, v in self.deadband.items() if k in FIELD_NAMES})
        return out

    @field_validator("password")
    @classmethod
    def _password_needs_username(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is not None and info.data.get("username", "") is None:
            raise fail("needs a username")
        return value

    @field_validator("state_expiry_s")
    @classmethod
    def _needs_mqtt5(cls, value: int | None, info: ValidationInfo) -> int | None:
        if value is not None and info.data.get("protocol") == "3.1.1":
            raise fail("needs protocol: 5 (MQTT 3.1.1 has no message expiry)")
        return value

    @field_validator("ca_file", "certfile", "keyfile")
    @classmethod
    def _tls_only(cls, value: str | None, info: ValidationInfo) -> str | None:
        url = info.data.get("url")
        first = url if isinstance(url, str) else (url or [None])[0]
        if value is not None and first is not None and not first.startswith("mqtts://"):
            raise fail("needs an mqtts:// url (TLS)")
        if info.field_name == "keyfile" and value is not None and \
                info.data.get("certfile", "") is None:
            raise fail("needs a certfile")
        return value

    @property
    def urls(self) -> tuple[str, ...]:
        return (self.url,) if isinstance(self.url, str) else tuple(self.url)

    @property
    def tls(self) -> bool:
        return self.urls[0].startswith("mqtts://")

    @property
    def brokers(self) -> tuple[Broker, ...]:
        return tuple(Broker.of(url) for url in self.urls)


class OpcUaConfig(_Model):
    """The OPC UA server (docs/opcua.md)."""

    listen: Listen = Field(default=ListenAddress("0.0.0.0", 4840), description=(
        "`host:port` as for `modbus.listen`, port not 0; the endpoint is "
        "`opc.tcp://{host}:{port}/`"))
    allow_none: bool = Field(default=False, description=(
        "also offer security mode None (no signing, no encryption); off: Basic256Sha256 "
        "Sign and SignAndEncrypt only"))
    anonymous: bool = Field(default=True, description=(
        "let clients in without a user name; must be false with `allow_commands`"))
    users: dict[NonEmpty, str] = Field(default_factory=dict, description=(
        "user name → password (write `${VAR}` to take it from the environment)"))
    allow_commands: bool = Field(default=False, description=(
        "each sensor offers the catalogue's commands as methods"))
    pki_dir: NonEmpty = Field(default="opcua-pki", description=(
        "the server's certificate and key (made at the first start if missing), and "
        "`trusted/`: the client certificates it accepts (DER or PEM)"))

    @model_validator(mode="after")
    def _access_rules(self) -> Self:
        if self.listen.port == 0:
            raise fail("listen: port 0 is not for OPC UA: the server advertises its "
                        "endpoint URL with its port, and clients connect to that; give "
                        "a port (4840 is OPC UA's)")
        if self.allow_commands and self.anonymous:
            raise fail("anonymous: true with allow_commands: true lets anyone run "
                        "commands; set anonymous: false and list users")
        if not self.anonymous and not self.users:
            raise fail("anonymous: false needs users, or nobody can log in")
        return self


#: Who may do what over HTTP (docs/rest.md, "Roles"): each role may do all a lower may.
Role = Literal["viewer", "operator", "admin"]


def _password_hash(value: str) -> str:
    try:
        passwords.parse(value)
    except ValueError as exc:
        raise fail(str(exc)) from None
    return value


class HttpUser(_Model):
    """One person who logs in to the dashboard or ``POST /api/v1/login``."""

    role: Role = Field(description="`viewer`, `operator` or `admin`")
    password: Annotated[str, AfterValidator(_password_hash)] = Field(description=(
        "the password's hash, as `imu-gateway hash-password` prints it (never the "
        "password itself); write `${VAR}` to take it from the environment"))


class HttpToken(_Model):
    """A bearer token a program sends (``Authorization: Bearer …``), and its role."""

    token: NonEmpty = Field(description=(
        "not empty; write `${VAR}` to take it from the environment"))
    role: Role = Field(description="`viewer`, `operator` or `admin`")


class HttpConfig(_Model):
    """The REST API and dashboard."""

    listen: Listen = Field(default=ListenAddress("0.0.0.0", 8080), description=(
        "`host:port` as for `modbus.listen`"))
    token: NonEmpty | None = Field(default=None, description=(
        "not empty; an admin's bearer token (`Authorization: Bearer …`), as before roles: "
        "the same as an entry of `tokens` with role `admin`; write `${VAR}` to take it "
        "from the environment"))
    tokens: tuple[HttpToken, ...] = Field(default=(), description=(
        "bearer tokens with their roles: a list of `{token, role}` (a list, not a map: "
        "`${VAR}` is expanded in values, not in keys)"),
        json_schema_extra={_SHOWN_DEFAULT: "`[]`"})
    users: dict[Name, HttpUser] = Field(default_factory=dict, description=(
        "user name → `{role, password}`: who may log in (`POST /api/v1/login`, the "
        "dashboard's form)"))
    session_minutes: Annotated[int, between(1, 7 * 24 * 60)] = Field(default=480, description=(
        "1-10080; how long a login's session token lasts"))
    allow_commands: bool = Field(default=False, description=(
        "accept `POST /api/v1/sensors/{name}/commands/{command}` (an operator's); needs "
        "`token`, `tokens` or `users`"))
    read_token_required: bool = Field(default=False, description=(
        "reads need a credential too (a viewer's at least); needs `token`, `tokens` or "
        "`users`"))

    @field_validator("allow_commands", "read_token_required")
    @classmethod
    def _needs_credentials(cls, value: bool, info: ValidationInfo) -> bool:
        given = info.data
        if value and given.get("token", "") is None and not given.get("tokens", 1) \
                and not given.get("users", 1):  # (a field that failed is absent: no 2nd error)
            raise fail("needs http.token, http.tokens or http.users (the credentials "
                       "clients must send)")
        return value

    @field_validator("tokens")
    @classmethod
    def _tokens_once(cls, value: tuple[HttpToken, ...]) -> tuple[HttpToken, ...]:
        given = [t.token for t in value]
        if len(set(given)) != len(given):
            raise fail("the same token twice (each token has one role)")
        return value

    def roles_of_tokens(self) -> dict[str, Role]:
        """Each bearer token's role: ``token`` is an admin's (as it was before roles)."""
        roles: dict[str, Role] = {t.token: t.role for t in self.tokens}
        if self.token is not None:
            roles[self.token] = "admin"
        return roles


#: An alarm's name as ``capture.on_alarms`` lists it (the alarms' own rule).
_ALARM_NAME = re.compile(r"[a-z0-9_]+")
#: The longest pre- and post-trigger windows: the ring's memory grows with ``pre_s``.
CAPTURE_MAX_S = 300


def _capture_span(low: float) -> AfterValidator:
    def check(value: float) -> float:
        if not low <= value <= CAPTURE_MAX_S:
            raise fail(f"must be {low:g}-{CAPTURE_MAX_S} seconds, not {value:g}")
        return value

    return AfterValidator(check)


def _positive_mb(value: float) -> float:
    if value <= 0:
        raise fail(f"must be > 0 (megabytes), not {value:g}")
    return value


def _alarm_names(value: object) -> Literal["all"] | tuple[str, ...]:
    if value == "all":
        return "all"
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise fail(f"must be \"all\" or a list of alarm names, not {show(value)}")
    for name in value:
        if not _ALARM_NAME.fullmatch(name):
            raise fail(f"an alarm name matches [a-z0-9_]+, not {show(name)}")
    return tuple(dict.fromkeys(value))


class CaptureConfig(_Model):
    """Event capture (docs/alarms.md, "Captures"): every sample and frame kept for
    ``pre_s``, written to a ZIP around each trigger."""

    dir: NonEmpty = Field(default="captures", description=(
        "the folder the captures go to (made at start if missing; a full or read-only "
        "one is a warning and a counter, never a stop)"))
    pre_s: Annotated[float, _capture_span(0.1)] = Field(default=10.0, description=(
        f"0.1-{CAPTURE_MAX_S}; seconds kept before a trigger (every sample of every "
        "sensor, every frame of every line: the ring in memory)"))
    post_s: Annotated[float, _capture_span(0.0)] = Field(default=10.0, description=(
        f"0-{CAPTURE_MAX_S}; seconds recorded after a trigger before the capture is "
        "written"))
    on_alarms: Annotated[Literal["all"] | tuple[str, ...],
                         PlainValidator(_alarm_names)] = Field(
        default=(), description=(
            "`all`, or a list of alarm names: an alarm of that name becoming active (on "
            "any sensor) triggers a capture. Empty: on demand only "
            "(`POST /api/v1/captures`)"),
        json_schema_extra={_SHOWN_TYPE: "\"all\" or list of names", _SHOWN_DEFAULT: "`[]`"})
    max_files: PositiveInt = Field(default=100, description=(
        "> 0; the most captures kept: the oldest are deleted first"))
    max_mb: Annotated[float, AfterValidator(_positive_mb)] = Field(default=500.0, description=(
        "> 0; the most megabytes (10^6 bytes) the captures take: the oldest are deleted "
        "first"))


class GatewayConfig(_Model):
    """The whole file.  A section left out (``None``) is an interface turned off."""

    gateway_id: GatewayId = Field(
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
    opcua: OpcUaConfig | None = Field(default=None, description=(
        "the OPC UA server (`opcua`); left out: off"))
    alarm_journal: FileToKeep | None = Field(default=None, description=(
        "a file the alarms' transitions are appended to (JSON lines; its folder must "
        "exist), read back at start: the alarms take up the states it last recorded "
        "([alarms.md](alarms.md#the-journal)); null: the journal is kept in memory only"))

    capture: CaptureConfig | None = Field(default=None, description=(
        "event capture (`capture`); left out: off, and no ring is kept"))
    hand_over_ms: Annotated[int, Field(ge=0, le=100)] = Field(default=0, description=(
        "0-100; the longest the buses' readings wait to be handed to the front ends "
        "that push them (MQTT, Sparkplug B, live streams): 0 hands each turn of the "
        "lines over at once (the least latency); 20 on a small box takes a fifth off "
        "the gateway's CPU with every front end on, for about 10 ms more latency at the "
        "median ([deployment.md](deployment.md#small-boxes)). Nothing is dropped, and "
        "nothing else waits: REST, Modbus TCP and OPC UA reads, a command's answer and a "
        "fresh read see each reading at once"))

    @model_validator(mode="before")
    @classmethod
    def _context_defaults(cls, data: Any) -> Any:
        return fill_defaults(data)

    @model_validator(mode="after")
    def _cross_check(self) -> Self:
        # Not a ValueError on purpose: it carries several problems, each with its path.
        problems = cross_problems(_views(self)) + self._unknown_capture_alarms()
        if problems:
            raise ConfigError(problems)
        return self

    def _unknown_capture_alarms(self) -> list[str]:
        """``capture.on_alarms`` names alarms some sensor has (a typo would never
        trigger, silently)."""
        if self.capture is None or self.capture.on_alarms == "all":
            return []
        known = {a.name for _, s in self.iter_sensors() for a in s.alarms} | {"communication"}
        return [f"capture.on_alarms[{i}]: no sensor has an alarm {name!r} (its alarms: "
                f"{', '.join(sorted(known))})"
                for i, name in enumerate(self.capture.on_alarms) if name not in known]

    def iter_sensors(self) -> Iterator[tuple[BusConfig, SensorConfig]]:
        """Every sensor with its bus, in file order."""
        for bus in self.buses:
            for sensor in bus.sensors:
                yield bus, sensor

    def interfaces(self) -> list[str]:
        """The interfaces turned on: ``modbus``, ``mqtt``, ``http``, ``opcua``, in that
        order."""
        return [n for n in ("modbus", "mqtt", "http", "opcua") if getattr(self, n) is not None]

    def summary(self) -> str:
        """``gateway lab-1, 2 buses, 3 sensors; interfaces: modbus, http``."""
        buses = len(self.buses)
        sensors = sum(len(bus.sensors) for bus in self.buses)
        return (
            f"gateway {self.gateway_id}, {buses} bus{'es' if buses != 1 else ''}, "
            f"{sensors} sensor{'s' if sensors != 1 else ''}; "
            f"interfaces: {', '.join(self.interfaces()) or 'none'}"
        )


def _views(config: GatewayConfig) -> list[BusView]:
    """The config as the checks across keys read it (``checks.py``)."""
    return [
        BusView(f"buses[{i}]", bus.name, bus.port, bus.protocol, [
            SensorView(f"buses[{i}].sensors[{j}]", s.name, s.address, s.unit_id,
                       s.raw_unit_id, s.stream_hz)
            for j, s in enumerate(bus.sensors)
        ])
        for i, bus in enumerate(config.buses)
    ]


# ------------------------------------------------------------ defaults from context


def _plain(item: Any) -> Any:
    """A model instance as the dict of what was given, so its defaults are filled again."""
    if isinstance(item, BaseModel):
        return item.model_dump(exclude_unset=True)
    if isinstance(item, Mapping):
        return dict(item)
    return item


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
    protocol = protocol_or_none(bus.get("protocol"))
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


def fill_defaults(data: Any) -> Any:
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
