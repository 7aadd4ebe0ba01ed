"""The command catalogue (docs/commands.md): the same names on REST, MQTT, Modbus TCP and CLI.

One row per command (``CATALOGUE``): its argument model (pydantic, so every front end
gets the same validation and the same messages), its summary, the series that have
it, what it does to the bus, what its answer teaches about the sensor's settings, and
its Modbus TCP register.  REST's routes, MQTT's topics, the Modbus TCP command block and
``docs/commands.md`` are all derived from these rows.

How a command goes on the wire is the protocol rows' business (``protocol.exchanges``:
one row per command per protocol), since that is where the frames are; a protocol
without a row for a command cannot carry it.  Adding a command: a row here, a row in
each protocol that has it, the sensor's side in the simulator, and
``scripts/command-reference`` (docs/architecture.md walks through one).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar, Literal, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .errors import ErrorKind, RequestFailed
from .model import KnownSettings, Series, WireProtocol
from .protocol.bcd import ANGLE, DECLINATION, BcdFormat
from .protocol.exchanges import adapter_for
from .protocol.native import BAUD_CODES


class _Args(BaseModel):
    # strict: JSON's true is not the number 1, and "5" is not 5
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class NoArgs(_Args):
    pass


class ZeroTypeArgs(_Args):
    type: Literal["absolute", "relative"]


def _at_resolution(value: Any, fmt: BcdFormat) -> Any:
    """A number rounded to what the sensor can hold, halves away from zero (0.25 is
    0.3 at one decimal, as the sensor shows it), before the range is checked: a Modbus
    client's float32 99.9 is 99.90000153, and must pass as the 99.9 it means.  Anything
    else goes on unchanged, for the strict type check to refuse."""
    if isinstance(value, float | int) and not isinstance(value, bool) and math.isfinite(value):
        return fmt.rounded(value)
    return value


class _DegreesArgs(_Args):
    """An angle the sensor takes in BCD (``_format``): rounded to that resolution, half
    away from zero, before its range is checked."""

    _format: ClassVar[BcdFormat]

    @field_validator("degrees", mode="before", check_fields=False)
    @classmethod
    def _round(cls, value: Any) -> Any:
        return _at_resolution(value, cls._format)


class HeadingArgs(_DegreesArgs):
    # 2.20 sends SXXX.YY, a signed angle: every value it can carry is accepted (Modbus
    # carries less, -200 to 455.35, and its encoding refuses the rest).
    _format = ANGLE
    degrees: float = Field(ge=-ANGLE.max_value, le=ANGLE.max_value, allow_inf_nan=False,
                           description="heading start point, degrees (0.01 resolution, "
                                       "rounded half away from zero)")


class DeclinationArgs(_DegreesArgs):
    # 2.21 sends SXX.Y: two integer digits and one decimal.
    _format = DECLINATION
    degrees: float = Field(ge=-DECLINATION.max_value, le=DECLINATION.max_value,
                           allow_inf_nan=False,
                           description="magnetic declination, degrees (0.1 resolution, "
                                       "rounded half away from zero)")


class MagCalibrationArgs(_Args):
    action: Literal["start", "finish", "clear"]


class AddressArgs(_Args):
    address: int = Field(ge=0, le=255, description="native 0-255, Modbus 1-247")


class BaudrateArgs(_Args):
    baudrate: int = Field(description=f"one of {', '.join(map(str, sorted(BAUD_CODES.values())))}")

    @field_validator("baudrate")
    @classmethod
    def _known(cls, value: int) -> int:
        if value not in BAUD_CODES.values():
            raise ValueError(f"must be one of {sorted(BAUD_CODES.values())}")
        return value


class BusEffect(enum.Enum):
    """What a command may do to the bus besides its exchange.  The protocol rows in
    ``protocol.exchanges`` carry it out, where their protocol needs it (a native gyro
    calibration is over when answered; a Modbus one keeps the sensor busy); a test
    holds the two to each other."""

    NONE = "none"
    BUSY = "the sensor is busy for a while"
    NEW_ADDRESS = "the sensor answers at its new address"
    NEW_BAUD = "the line follows the new baud rate"


Args = Mapping[str, Any]
#: What a successful command's arguments and answer show of the sensor's settings.
Learn = Callable[[Args, Args], KnownSettings]


def _nothing(args: Args, answer: Args) -> KnownSettings:
    return KnownSettings()


@dataclass(frozen=True, slots=True)
class TcpRegister:
    """The command's holding register in the Modbus TCP map (docs/register-map.md).
    Writing it runs the command: 1 for a command without arguments, ``codes`` for a
    choice, a float32 for degrees.  Reading it gives the known ``setting`` (a field of
    ``KnownSettings``; Home Assistant's select and number entities show the same): a
    choice as its code (``unknown`` when not known), a float (NaN when not known).
    Without a setting, a command that keeps the sensor busy reads 1 while it runs,
    any other 0.  The address is part of the public map: never move one."""

    address: int
    name: str
    description: str
    setting: str | None = None
    codes: Mapping[str, int] = field(default_factory=dict)
    unknown: int = 0xFFFF


@dataclass(frozen=True, slots=True)
class CommandSpec:
    """One command, as every front end knows it (REST, MQTT, Modbus TCP, the CLI)."""

    name: str
    args: type[_Args]
    summary: str
    series: frozenset[Series]
    bus: BusEffect = BusEffect.NONE
    #: what a successful answer teaches about the sensor's settings
    learns: Learn = _nothing
    register: TcpRegister | None = None
    #: arguments to show in examples (the dashboard's, the demo's, the docs')
    example: Args = field(default_factory=dict)
    #: sent twice, it leaves the sensor as sent once: sent again when its answer is
    #: lost.  Any other command is not, since the lost answer may be the only thing
    #: lost; it fails as ``unconfirmed`` instead (docs/bus-master.md, "Retries").
    idempotent: bool = False

    @property
    def argument(self) -> str | None:
        """The name of its one argument (no command takes more), or ``None``: what a
        Modbus TCP register or a Home Assistant entity carries."""
        names = list(self.args.model_fields)
        assert len(names) <= 1, f"{self.name}: one argument at most"
        return names[0] if names else None


ALL, AH, MINS = frozenset(Series), frozenset({Series.AH}), frozenset({Series.MINS})

#: The catalogue, one row per command; its order is the docs' and the API's.
CATALOGUE: Mapping[str, CommandSpec] = MappingProxyType({
    spec.name: spec
    for spec in (
        CommandSpec(
            # (not idempotent: a relative zero is the attitude when it is heard)
            "set_zero_type", ZeroTypeArgs, "absolute or relative zero point", ALL,
            learns=lambda args, answer: KnownSettings(zero_type=args["type"]),
            register=TcpRegister(1000, "zero_type", "zero type: write 0 absolute, 1 relative; "
                                 "reads the last known (0xFFFF unknown)", "zero_type",
                                 {"absolute": 0, "relative": 1}),
            example={"type": "relative"}),
        CommandSpec(
            "save", NoArgs, "save the settings (3-5 s, the sensor does not answer)", ALL,
            BusEffect.BUSY, lambda args, answer: KnownSettings(busy_with="save"),
            TcpRegister(1001, "save", "write 1: save settings; reads 1 while saving")),
        CommandSpec(
            "calibrate_gyro", NoArgs, "gyro zero-offset calibration (keep still)", ALL,
            BusEffect.BUSY, lambda args, answer: KnownSettings(busy_with="calibrate_gyro"),
            TcpRegister(1002, "gyro_calibration", "write 1: gyro calibration; reads 1 while "
                        "it runs")),
        CommandSpec(
            "clear_heading", NoArgs, "clear the heading angle (MINS)", MINS,
            register=TcpRegister(1003, "clear_heading", "write 1: clear heading (MINS); "
                                 "reads 0")),
        CommandSpec(
            "set_relative_heading", HeadingArgs, "heading start point (MINS)", MINS,
            # the sensor's echo, at its resolution (what it holds)
            learns=lambda args, answer: KnownSettings(
                relative_heading=answer.get("degrees", args["degrees"])),
            register=TcpRegister(1004, "relative_heading", "relative heading start point, "
                                 "degrees (MINS), rounded to 0.01 half away from zero; reads "
                                 "the last written (NaN unknown)", "relative_heading"),
            example={"degrees": 90.0}, idempotent=True),
        CommandSpec(
            "set_declination", DeclinationArgs, "magnetic declination (AH)", AH,
            # the sensor's echo: -1.25 is sent and stored as -1.3
            learns=lambda args, answer: KnownSettings(
                declination=answer.get("degrees", args["degrees"])),
            register=TcpRegister(1006, "declination", "magnetic declination, degrees (AH), "
                                 "-99.9 to 99.9, rounded to 0.1 half away from zero; reads "
                                 "the last known (NaN unknown)", "declination"),
            example={"degrees": -3.5}, idempotent=True),
        CommandSpec(
            "mag_calibration", MagCalibrationArgs,
            "plane circumference calibration: start, finish, clear (AH)", AH,
            learns=lambda args, answer: KnownSettings(mag_calibration=args["action"]),
            register=TcpRegister(1008, "mag_calibration", "magnetic calibration: write 1 "
                                 "start, 2 finish, 3 clear (AH); reads the last action "
                                 "(0 none)", "mag_calibration",
                                 {"start": 1, "finish": 2, "clear": 3}, unknown=0),
            example={"action": "start"}),
        CommandSpec("set_address", AddressArgs, "a new bus address", ALL,
                    BusEffect.NEW_ADDRESS, example={"address": 5}),
        CommandSpec("set_baudrate", BaudrateArgs, "a new baud rate; the gateway follows", ALL,
                    BusEffect.NEW_BAUD, example={"baudrate": 115200}),
        CommandSpec(
            "read_settings", NoArgs, "zero type, address, declination (AH)", ALL,
            learns=lambda args, answer: KnownSettings(zero_type=answer.get("zero_type"),
                                                      declination=answer.get("declination")),
            idempotent=True),
    )
})


def argument_type(spec: CommandSpec) -> type[str] | type[int] | type[float] | None:
    """The type of a command's one argument as a client writes it (a choice is a
    string); None: no argument."""
    if spec.argument is None:
        return None
    annotation: Any = spec.args.model_fields[spec.argument].annotation
    if get_origin(annotation) is Literal or annotation is str:
        return str
    return int if annotation is int else float


def resolution(spec: CommandSpec) -> float | None:
    """The step of a command's angle argument (0.01° heading, 0.1° declination), if
    it has one."""
    return spec.args._format.resolution if issubclass(spec.args, _DegreesArgs) else None


def commands_for(series: Series, protocol: WireProtocol) -> frozenset[str]:
    """The commands a sensor of this series, speaking this protocol, can carry out: the
    series has it (the catalogue) and the protocol can carry it (its rows)."""
    carries = adapter_for(protocol).carries
    return frozenset(name for name, spec in CATALOGUE.items()
                     if series in spec.series and carries(name))


@dataclass(frozen=True, slots=True)
class Command:
    """A validated command for one sensor."""

    name: str
    args: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class CommandResult:
    """The sensor's answer, or why there is none."""

    sensor: str
    command: str
    ok: bool
    answer: Mapping[str, Any] = field(default_factory=dict)
    error: str | None = None
    kind: ErrorKind | None = None

    @classmethod
    def failed(cls, sensor: str, command: str, error: RequestFailed) -> CommandResult:
        return cls(sensor, command, False, {}, str(error), error.kind)

    def to_json(self) -> dict[str, Any]:
        return {"ok": self.ok, "sensor": self.sensor, "command": self.command,
                "answer": dict(self.answer), "error": self.error,
                "kind": self.kind.value if self.kind else None}


def _friendly(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"]) or "arguments"
        message = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            message = "unknown argument"
        parts.append(f"{where}: {message}")
    return "; ".join(parts)


def unknown_command(name: str) -> RequestFailed:
    """The one way every front end words a command the catalogue lacks."""
    return RequestFailed(ErrorKind.UNKNOWN_COMMAND,
                         f"unknown command {name!r} (known: {', '.join(CATALOGUE)})")


def validate(name: str, args: Mapping[str, Any] | None, series: Series,
             protocol: WireProtocol) -> Command:
    """Check a command for a sensor of ``series``; raises ``RequestFailed``."""
    spec = CATALOGUE.get(name)
    if spec is None:
        raise unknown_command(name)
    if name not in commands_for(series, protocol):
        # the series has it, so the protocol cannot carry it
        over = " over Modbus" if series in spec.series else ""
        raise RequestFailed(ErrorKind.UNSUPPORTED, f"{series.name} sensors have no {name}{over}")
    if args is not None and not isinstance(args, Mapping):
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, "arguments must be a JSON object")
    try:
        parsed = spec.args.model_validate(dict(args or {}))
    except ValidationError as exc:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"{name}: {_friendly(exc)}") from None
    values = parsed.model_dump()
    modbus = protocol is WireProtocol.MODBUS
    if name == "set_address" and modbus and not 1 <= values["address"] <= 247:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, "set_address: a Modbus address is 1-247")
    return Command(name, values)
