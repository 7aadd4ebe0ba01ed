"""The command catalogue (docs/commands.md): the same names on REST, MQTT, Modbus TCP and CLI.

One table: each command's argument model (pydantic, so every front end gets the same
validation and the same messages) and its summary.  Which series has which command
comes from the capability table in ``model``; which protocol can carry it is the
protocol adapter's business (``protocol.exchanges``), since that is where the frames
are.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .errors import ErrorKind, RequestFailed
from .model import CAPABILITIES, Series, WireProtocol, commands_for
from .protocol.bcd import ANGLE, DECLINATION, BcdFormat
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
    baudrate: int

    @field_validator("baudrate")
    @classmethod
    def _known(cls, value: int) -> int:
        if value not in BAUD_CODES.values():
            raise ValueError(f"must be one of {sorted(BAUD_CODES.values())}")
        return value


@dataclass(frozen=True, slots=True)
class CommandSpec:
    name: str
    args: type[_Args]
    summary: str


CATALOGUE: Mapping[str, CommandSpec] = {
    spec.name: spec
    for spec in (
        CommandSpec("set_zero_type", ZeroTypeArgs, "absolute or relative zero point"),
        CommandSpec("save", NoArgs, "save the settings (3-5 s, the sensor does not answer)"),
        CommandSpec("calibrate_gyro", NoArgs, "gyro zero-offset calibration (keep still)"),
        CommandSpec("clear_heading", NoArgs, "clear the heading angle (MINS)"),
        CommandSpec("set_relative_heading", HeadingArgs, "heading start point (MINS)"),
        CommandSpec("set_declination", DeclinationArgs, "magnetic declination (AH)"),
        CommandSpec("mag_calibration", MagCalibrationArgs,
                    "plane circumference calibration: start, finish, clear (AH)"),
        CommandSpec("set_address", AddressArgs, "a new bus address"),
        CommandSpec("set_baudrate", BaudrateArgs, "a new baud rate; the gateway follows"),
        CommandSpec("read_settings", NoArgs, "zero type, address, declination (AH)"),
    )
}


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
        over = " over Modbus" if name in CAPABILITIES[series].commands else ""
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
