"""Procedures: the calibration and setup wizards (docs/wizards.md), sans-IO.

A procedure is a few catalogue commands (``commands.CATALOGUE``) with what a person
does between them: keep the sensor still, turn it through a circle.  Every step is a
command any front end can send, so an MQTT or OPC UA user can do the same by hand;
REST runs a procedure as a resource (``frontends.rest.procedures``), one step after
the other, and streams its progress.

One row per procedure (``PROCEDURES``): its argument model, the series it applies to,
its steps.  ``Run`` carries one out as a state machine with no clock and no I/O:
the driver hands it the time, the command answers and the sensor's snapshots, and
asks it what to do next (``Run.action``): send a command, or wait until a moment or
for the next input.  The tests drive it in virtual time.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from .commands import CATALOGUE, AddressArgs, BaudrateArgs, CommandResult
from .config import GatewayConfig
from .config.fields import ADDRESS_RANGE
from .errors import ErrorKind, RequestFailed
from .model import Angles, Reading, Series, WireProtocol
from .protocol.exchanges import GYRO_CAL_SECONDS

Args = Mapping[str, Any]

#: The circle is cut into this many sectors of atan2(mag_y, mag_x) (10° each); its
#: coverage is the share of sectors a reading fell in.
SECTORS = 36
#: At most one point per degree of the circle is kept for the plot (the latest).
MAX_POINTS = 360


class _Args(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class GyroArgs(_Args):
    countdown_s: float = Field(5.0, ge=0, le=60, allow_inf_nan=False,
                               description="seconds to let go of the sensor before the "
                                           "calibration starts")


class MagArgs(_Args):
    pass


class ZeroArgs(_Args):
    type: Literal["absolute", "relative"]
    relative_heading: float | None = Field(
        None, ge=-999.99, le=999.99, allow_inf_nan=False,
        description="MINS only: the heading start point, degrees (set_relative_heading)")


class AddressChangeArgs(AddressArgs):
    """The new bus address (``set_address``'s own argument, checked by the catalogue)."""


class BaudChangeArgs(BaudrateArgs):
    """The new baud rate (``set_baudrate``'s own argument, checked by the catalogue)."""


# ------------------------------------------------------------------ where it is


@dataclass(frozen=True, slots=True)
class Placement:
    """A sensor's place as the running gateway has it: what an address or baud change
    is checked against, and what its messages name."""

    sensor: str
    bus: str
    protocol: WireProtocol
    port: str
    baudrate: int
    address: int
    #: the bus's other sensors and the addresses they hold (the config's, and the
    #: live one where a ``set_address`` moved it)
    others: tuple[tuple[str, int], ...] = ()

    @classmethod
    def of(cls, config: GatewayConfig, sensor: str,
           live: Mapping[str, int] | None = None) -> Placement:
        """``live``: the address each sensor is talked to at now, by name."""
        live = live or {}
        bus = next(b for b, s in config.iter_sensors() if s.name == sensor)
        me = next(s for s in bus.sensors if s.name == sensor)
        others = tuple(dict.fromkeys(
            (s.name, a) for s in bus.sensors if s.name != sensor
            for a in (s.address, live.get(s.name, s.address))))
        return cls(sensor, bus.name, bus.protocol, bus.port, bus.baudrate,
                   live.get(sensor, me.address), others)


def _check_address(args: Args, where: Placement) -> None:
    new = args["address"]
    low, high = ADDRESS_RANGE[where.protocol]
    if not low <= new <= high:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"address: a {where.protocol.name.lower()} "
                            f"address is {low}-{high}, not {new}")
    if new == where.address:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"{where.sensor} is at address {new} "
                            "already: give another")
    taken = sorted({name for name, address in where.others if address == new})
    if taken:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, (
            f"address {new} is taken on bus {where.bus} by {', '.join(taken)}: two "
            "sensors at one address garble each other's answers; choose a free one"))


def _check_baud(args: Args, where: Placement) -> None:
    new = args["baudrate"]
    if new == where.baudrate:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"bus {where.bus} runs at {new} baud "
                            "already: give another rate")
    others = sorted({name for name, _ in where.others})
    if others:
        # One sensor moved leaves the line split: the others would go offline at the
        # rate the gateway follows.  Each is moved by hand (docs/wizards.md).
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, (
            f"bus {where.bus} has other sensors ({', '.join(others)}), which would stay at "
            f"{where.baudrate} baud and go offline: the wizard changes a bus of one "
            "sensor only (docs/wizards.md says how to move a whole bus by hand)"))
    if where.port.startswith("socket://"):
        raise RequestFailed(ErrorKind.UNSUPPORTED, (
            f"bus {where.bus} is a raw TCP port ({where.port}): the gateway cannot change "
            "the serial server's rate, so the sensor would be lost; change the rate on the "
            "server and the sensor together by hand"))


def _address_change(args: Args, where: Placement) -> ConfigChange:
    return ConfigChange(where.bus, where.sensor, "address", args["address"])


def _baud_change(args: Args, where: Placement) -> ConfigChange:
    return ConfigChange(where.bus, None, "baudrate", args["baudrate"])


# ------------------------------------------------------------------ the steps


@dataclass(frozen=True, slots=True)
class Countdown:
    """Wait ``seconds_of(args)`` with ``prompt`` shown (let go of the sensor)."""

    prompt: str
    seconds_of: Callable[[Args], float]


@dataclass(frozen=True, slots=True)
class Send:
    """Send a catalogue command; ``args_of`` gives its arguments, or None to skip it."""

    command: str
    args_of: Callable[[Args], Args | None] = lambda args: {}
    prompt: str = ""
    #: left out unless its arguments ask for it (a sensor without it may still run
    #: the procedure)
    optional: bool = False


@dataclass(frozen=True, slots=True)
class UntilIdle:
    """Wait while the sensor is busy (a Modbus gyro calibration reports when it is
    done; a native one is over when answered, so this passes at once)."""

    prompt: str
    limit_s: float


@dataclass(frozen=True, slots=True)
class Circle:
    """Collect mag x against mag y until every sector of the circle is covered, or
    the person says ``finish``."""

    prompt: str


@dataclass(frozen=True, slots=True)
class Look:
    """Note the angles of the next reading taken after this step began (``label``:
    before or after)."""

    label: Literal["before", "after"]
    prompt: str = "reading the angles"


@dataclass(frozen=True, slots=True)
class Reconfigure:
    """Change the config to match the sensor (``ProcedureSpec.change``), through the
    reload: the driver applies and saves it, and calls ``Run.reconfigured``."""

    prompt: str = "updating the config (a reload) and saving it"


@dataclass(frozen=True, slots=True)
class Heard:
    """Wait for a reading newer than this step (the gateway hears the sensor where it
    is now); fail after ``limit_s``."""

    prompt: str
    limit_s: float


Step = Countdown | Send | UntilIdle | Circle | Look | Reconfigure | Heard


@dataclass(frozen=True, slots=True)
class ConfigChange:
    """One value of the config: a sensor's (``sensor`` given) or its bus's."""

    bus: str
    sensor: str | None
    key: str
    value: int

    def applied_to(self, data: Any) -> Any:
        """The config's data (as ``GET /api/v1/config`` shows it) with this value set;
        raises ``ValueError`` when the bus or the sensor is not in it."""
        buses = data.get("buses") if isinstance(data, Mapping) else None
        bus: dict[str, Any] | None = next((b for b in buses or () if isinstance(b, dict)
                                           and b.get("name") == self.bus), None)
        if bus is None:
            raise ValueError(f"the config has no bus {self.bus!r} now")
        target: dict[str, Any] | None = bus
        if self.sensor is not None:
            target = next((s for s in bus.get("sensors") or () if isinstance(s, dict)
                           and s.get("name") == self.sensor), None)
        if target is None:
            raise ValueError(f"bus {self.bus} has no sensor {self.sensor!r} now")
        target[self.key] = self.value
        return data

    def where(self) -> str:
        return f"sensor {self.sensor} of bus {self.bus}" if self.sensor else f"bus {self.bus}"


@dataclass(frozen=True, slots=True)
class ProcedureSpec:
    """One procedure, as every front end knows it."""

    name: str
    summary: str
    series: frozenset[Series]
    args: type[BaseModel]
    steps: tuple[Step, ...]
    #: sent when it is cancelled after its first command (put the sensor back)
    cleanup: Send | None = None
    #: what the person is offered once it is done (a command's name)
    offers: tuple[str, ...] = ()
    #: checks the arguments against the sensor's place (raises ``RequestFailed``)
    check: Callable[[Args, Placement], None] | None = None
    #: the config change that follows the sensor (a ``Reconfigure`` step applies it):
    #: it changes the config, so it is an admin's (docs/wizards.md)
    change: Callable[[Args, Placement], ConfigChange] | None = None
    #: once its command was sent it cannot be undone, nor cancelled
    cancellable_after_send: bool = True
    #: sent when a command's answer was lost (``unconfirmed``): did it take?
    read_back: str | None = None
    #: the protocols on which an answered read back proves the change took (Modbus
    #: baud: the line switched before the read); on the others it proves it did not
    taken_if_read_back: frozenset[WireProtocol] = frozenset()

    @property
    def admin(self) -> bool:
        return self.change is not None

    @property
    def commands(self) -> frozenset[str]:
        return frozenset(s.command for s in (*self.steps, self.cleanup) if isinstance(s, Send))


def _heading(args: Args) -> Args | None:
    degrees = args.get("relative_heading")
    return None if degrees is None else {"degrees": degrees}


PROCEDURES: Mapping[str, ProcedureSpec] = MappingProxyType({spec.name: spec for spec in (
    ProcedureSpec(
        "gyro_calibration", "gyro zero-offset calibration: keep still, calibrate, wait",
        frozenset(Series), GyroArgs, (
            Countdown("Keep the sensor absolutely still", lambda a: float(a["countdown_s"])),
            Send("calibrate_gyro", prompt="Calibrating: keep the sensor still"),
            UntilIdle("Calibrating: keep the sensor still", GYRO_CAL_SECONDS + 2.0))),
    ProcedureSpec(
        "mag_calibration", "plane circumference calibration of the magnetometer (AH)",
        frozenset({Series.AH}), MagArgs, (
            Send("mag_calibration", lambda a: {"action": "clear"}),
            Send("mag_calibration", lambda a: {"action": "start"}),
            Circle("Turn the sensor slowly through one full circle in the horizontal plane"),
            Send("mag_calibration", lambda a: {"action": "finish"})),
        cleanup=Send("mag_calibration", lambda a: {"action": "clear"}), offers=("save",)),
    ProcedureSpec(
        "zero", "set the zero type (and a MINS's relative heading), angles before and after",
        frozenset(Series), ZeroArgs, (
            Look("before"),
            Send("set_zero_type", lambda a: {"type": a["type"]}),
            Send("set_relative_heading", _heading, optional=True),
            Look("after")),
        offers=("save",)),
    ProcedureSpec(
        "change_address", "a new bus address: checked free, set, verified, the config "
        "changed to match", frozenset(Series), AddressChangeArgs, (
            Send("set_address", lambda a: {"address": a["address"]},
                 prompt="Setting the address: keep the sensor powered"),
            Reconfigure(),
            Heard("waiting for a reading from the new address", 10.0)),
        offers=("save",), check=_check_address, change=_address_change,
        cancellable_after_send=False, read_back="read_settings"),
    ProcedureSpec(
        "change_baudrate", "a new baud rate for a bus of one sensor: set, verified, the "
        "config changed to match", frozenset(Series), BaudChangeArgs, (
            Send("set_baudrate", lambda a: {"baudrate": a["baudrate"]},
                 prompt="Setting the baud rate: keep the sensor powered"),
            Reconfigure(),
            Heard("waiting for a reading at the new rate", 10.0)),
        offers=("save",), check=_check_baud, change=_baud_change,
        cancellable_after_send=False, read_back="read_settings",
        taken_if_read_back=frozenset({WireProtocol.MODBUS})),
)})


def available(series: Series, commands: frozenset[str]) -> list[str]:
    """The procedures a sensor of ``series`` that can carry ``commands``
    (``commands.commands_for``) can run."""
    return [spec.name for spec in PROCEDURES.values() if series in spec.series and {
        s.command for s in spec.steps if isinstance(s, Send) and not s.optional} <= commands]


def unknown_procedure(name: str) -> RequestFailed:
    return RequestFailed(ErrorKind.NOT_FOUND, f"unknown procedure {name!r} (known: "
                                              f"{', '.join(PROCEDURES)})")


def validate(name: str, args: Args | None, series: Series, commands: frozenset[str],
             where: Placement | None = None) -> tuple[ProcedureSpec, Args]:
    """The procedure and its checked arguments for a sensor of ``series`` that can carry
    ``commands`` (``commands.commands_for``), at ``where`` (needed by those that
    ``check`` it); raises ``RequestFailed``."""
    spec = PROCEDURES.get(name)
    if spec is None:
        raise unknown_procedure(name)
    if series not in spec.series:
        raise RequestFailed(ErrorKind.UNSUPPORTED, f"{series.name} sensors have no {name} "
                            f"(it is for {', '.join(sorted(s.name for s in spec.series))})")
    if args is not None and not isinstance(args, Mapping):
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, "arguments must be a JSON object")
    try:
        values = spec.args.model_validate(dict(args or {})).model_dump()
    except ValidationError as exc:
        wrong = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'arguments'}: {e['msg']}"
                          for e in exc.errors())
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"{name}: {wrong}") from None
    # the commands these arguments need (a zero without relative_heading needs no heading)
    needed = {s.command for s in spec.steps if isinstance(s, Send)
              and s.args_of(values) is not None}
    missing = sorted(needed - commands)
    if missing:
        raise RequestFailed(ErrorKind.UNSUPPORTED, f"{name} needs {', '.join(missing)}, "
                            f"which this {series.name} sensor cannot carry (docs/commands.md)")
    if spec.check is not None:
        if where is None:
            raise RequestFailed(ErrorKind.UNSUPPORTED, f"{name} needs the sensor's bus")
        spec.check(values, where)
    return spec, values


# ------------------------------------------------------------------ the circle


@dataclass(frozen=True, slots=True)
class Quality:
    """How round and centred the circle of mag x against mag y is: its centre (the
    middle of its extremes) off the origin, as a share of its mean radius, and the
    ratio of its longer span to its shorter (1: a circle)."""

    centre_x: float
    centre_y: float
    centre_offset_percent: float
    ellipse_ratio: float

    def to_json(self) -> dict[str, float]:
        return {"centre_x": round(self.centre_x, 5), "centre_y": round(self.centre_y, 5),
                "centre_offset_percent": round(self.centre_offset_percent, 1),
                "ellipse_ratio": round(self.ellipse_ratio, 3)}


@dataclass(slots=True)
class CircleTrace:
    """The readings' mag x and y, by sector and by degree."""

    sectors: set[int] = field(default_factory=set)
    points: dict[int, tuple[float, float]] = field(default_factory=dict)  # by degree

    def add(self, x: float, y: float) -> None:
        if not (math.isfinite(x) and math.isfinite(y)) or (x == 0.0 and y == 0.0):
            return  # no direction
        degrees = math.degrees(math.atan2(y, x)) % 360.0
        self.sectors.add(int(degrees // (360 / SECTORS)) % SECTORS)
        self.points[int(degrees) % MAX_POINTS] = (x, y)

    @property
    def coverage_percent(self) -> float:
        return round(100.0 * len(self.sectors) / SECTORS, 1)

    def quality(self) -> Quality | None:
        """Only for a whole circle: the extremes of a part of one say nothing of it."""
        if len(self.sectors) < SECTORS:
            return None
        xs = [p[0] for p in self.points.values()]
        ys = [p[1] for p in self.points.values()]
        cx, cy = (max(xs) + min(xs)) / 2, (max(ys) + min(ys)) / 2
        span_x, span_y = max(xs) - min(xs), max(ys) - min(ys)
        radius = (span_x + span_y) / 4
        if min(span_x, span_y) <= 0 or radius <= 0:
            return None
        return Quality(cx, cy, 100.0 * math.hypot(cx, cy) / radius,
                       max(span_x, span_y) / min(span_x, span_y))

    def to_json(self) -> list[list[float]]:
        return [[round(x, 5), round(y, 5)] for _, (x, y) in sorted(self.points.items())]


# ------------------------------------------------------------------ the machine


class State(enum.Enum):
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"


@dataclass(frozen=True, slots=True)
class SendCommand:
    """What the driver does next: send this command, then call ``Run.answered``."""

    command: str
    args: Args


@dataclass(frozen=True, slots=True)
class ChangeConfig:
    """What the driver does next: apply ``change`` to the config through the reload
    (and save it), then call ``Run.reconfigured``."""

    change: ConfigChange


@dataclass(frozen=True, slots=True)
class Wait:
    """What the driver does next: wait until ``until`` (``None``: for the next input)
    and call ``Run.tick``, or feed what comes (``observe``, ``user``, ``cancel``)."""

    until: float | None


Action = SendCommand | ChangeConfig | Wait | None  # None: over


@dataclass(slots=True)
class Run:
    """One procedure carried out: feed it time and events, ask ``action``."""

    spec: ProcedureSpec
    args: Args
    started: float
    where: Placement | None = None  # (the procedures that ``check`` it have it)
    state: State = State.RUNNING
    index: int = -1  # the step under way
    step_began: float = 0.0
    seq: int = 0  # the latest reading's, as last observed
    look_after: int = 0  # a Look takes a reading with a higher seq than this
    busy: bool = False
    in_flight: bool = False  # a command is sent and not answered
    sent_any: bool = False
    cleaning: bool = False  # the cleanup command after a cancel is due or sent
    cleanup_sent: bool = False  # (the answer that ends the cleaning is the cleanup's own)
    reading_back: bool = False  # a command's answer was lost: ``spec.read_back`` is due
    lost: str | None = None  # that command's error
    error: str | None = None
    kind: ErrorKind | None = None
    answers: dict[str, Any] = field(default_factory=dict)
    angles: dict[str, dict[str, float]] = field(default_factory=dict)
    circle: CircleTrace = field(default_factory=CircleTrace)
    ended: float | None = None

    def __post_init__(self) -> None:
        self._next(self.started)

    @property
    def over(self) -> bool:
        return self.state is not State.RUNNING and not self.cleaning

    @property
    def step(self) -> Step | None:
        return self.spec.steps[self.index] if 0 <= self.index < len(self.spec.steps) else None

    def _next(self, now: float) -> None:
        """On to the next step that applies (a ``Send`` without arguments does not)."""
        while True:
            self.index += 1
            self.step_began, self.look_after = now, self.seq
            step = self.step
            if step is None:
                self._end(State.DONE, now)
                return
            if not (isinstance(step, Send) and step.args_of(self.args) is None):
                return

    def _end(self, state: State, now: float, error: str | None = None,
             kind: ErrorKind | None = None) -> None:
        self.state, self.error, self.kind, self.ended = state, error, kind, now

    def action(self, now: float) -> Action:
        """What to do next; ``tick`` first passes the time (countdowns, limits)."""
        self.tick(now)
        if self.in_flight:
            return Wait(None)
        if self.cleaning:
            assert self.spec.cleanup is not None
            return SendCommand(self.spec.cleanup.command, self.spec.cleanup.args_of(self.args)
                               or {})
        if self.state is not State.RUNNING:
            return None
        step = self.step
        if self.reading_back:
            assert self.spec.read_back is not None
            return SendCommand(self.spec.read_back, {})
        if isinstance(step, Send):
            return SendCommand(step.command, step.args_of(self.args) or {})
        if isinstance(step, Reconfigure):
            assert self.spec.change is not None and self.where is not None
            return ChangeConfig(self.spec.change(self.args, self.where))
        if isinstance(step, Countdown):
            return Wait(self.step_began + step.seconds_of(self.args))
        if isinstance(step, UntilIdle | Heard):
            return Wait(self.step_began + step.limit_s)
        return Wait(None)

    def tick(self, now: float) -> None:
        step = self.step
        if self.state is not State.RUNNING or self.in_flight:
            return
        if isinstance(step, Countdown) and now >= self.step_began + step.seconds_of(self.args):
            self._next(now)
        elif isinstance(step, UntilIdle):
            if not self.busy:
                self._next(now)
            elif now >= self.step_began + step.limit_s:
                self._end(State.FAILED, now, f"the sensor was still busy after "
                          f"{step.limit_s:g} s", ErrorKind.TIMEOUT)
        elif isinstance(step, Heard) and now >= self.step_began + step.limit_s:
            self._end(State.FAILED, now, f"no reading came within {step.limit_s:g} s of "
                      f"the reload, though the sensor answered {self._at(new=True)} and "
                      "the config says so now: look at its power and wiring, and at the "
                      "bus's errors (GET /api/v1/buses)", ErrorKind.TIMEOUT)

    def sending(self) -> None:
        """The driver sent the command ``action`` gave."""
        self.in_flight = self.sent_any = True
        self.cleanup_sent = self.cleanup_sent or self.cleaning

    def answered(self, result: CommandResult, now: float) -> None:
        self.in_flight = False
        if self.cleaning:
            # The cleanup's answer ends it (its outcome changes nothing: it was
            # cancelled); the answer of a command in flight when the cancel came does
            # not: the cleanup goes after it.
            self.cleaning = not self.cleanup_sent
            return
        if self.state is not State.RUNNING:
            return
        if self.reading_back:
            self._read_back(result, now)
            return
        if not result.ok and result.kind is ErrorKind.UNCONFIRMED and self.spec.read_back:
            self.reading_back, self.lost = True, f"{result.command}: {result.error}"
            return
        if not result.ok:
            self._end(State.FAILED, now, f"{result.command}: {result.error}", result.kind)
            return
        step = self.step
        assert isinstance(step, Send)
        action = step.args_of(self.args) or {}
        key = f"{result.command} {action['action']}" if "action" in action else result.command
        self.answers[key] = dict(result.answer)
        self._next(now)

    def _read_back(self, result: CommandResult, now: float) -> None:
        """The answer to ``spec.read_back`` after a command's was lost: did it take?"""
        self.reading_back = False
        assert self.where is not None
        self.answers[f"{result.command} (read back)"] = \
            dict(result.answer) if result.ok else {"error": result.error}
        sensor = self.where.sensor
        if result.ok and self.where.protocol in self.spec.taken_if_read_back:
            self._next(now)  # it answered where only the change puts it: it took
        elif result.ok:
            self._end(State.FAILED, now, f"{self.lost}; read back, {sensor} still answers "
                      f"{self._at(new=False)}: it was not changed, nor was the config; "
                      "run the wizard again", ErrorKind.UNCONFIRMED)
        else:
            self._end(State.FAILED, now, f"{self.lost}; the read back was not answered "
                      f"either: {sensor} may be {self._at(new=True)} now, or still "
                      f"{self._at(new=False)}. The config was not changed. Find it with a "
                      "scan of the line (the Setup page), then put what the scan found in "
                      "the config", ErrorKind.UNCONFIRMED)

    def _at(self, new: bool) -> str:
        """Where the sensor is (``new``: after the change): ``at address 5``."""
        assert self.spec.change is not None and self.where is not None
        change = self.spec.change(self.args, self.where)
        if change.key == "address":
            return f"at address {change.value if new else self.where.address}"
        return f"at {change.value if new else self.where.baudrate} baud"

    def reconfigured(self, outcome: Mapping[str, Any] | None, error: str | None,
                     now: float) -> None:
        """The driver applied the config change (``outcome``: the reload's, as
        ``PUT /api/v1/config`` answers), or could not (``error``)."""
        self.in_flight = False
        if self.state is not State.RUNNING:
            return
        if error is not None or outcome is None:
            self._end(State.FAILED, now, self._stranded(error or "no reload"))
            return
        self.answers["config"] = dict(outcome)
        self._next(now)

    def _stranded(self, why: str) -> str:
        """What state the sensor is in when the config could not follow it, and the fix."""
        assert self.spec.change is not None and self.where is not None
        change = self.spec.change(self.args, self.where)
        w = self.where
        if change.key == "address":
            state = (f"{w.sensor} now answers at address {change.value} (verified), and the "
                     "gateway talks to it there until it restarts")
            after = f"after a restart the gateway looks for it at address {w.address}"
        else:
            state = (f"{w.sensor} and bus {w.bus} now run at {change.value} baud (verified), "
                     "and the gateway follows until it restarts")
            after = f"after a restart the gateway opens the line at {w.baudrate} baud " \
                "and does not hear it"
        return (f"{state}; but the config could not follow: {why}. Put `{change.key}: "
                f"{change.value}` on {change.where()} in the config (the Setup page, or PUT "
                f"/api/v1/config), and send save to the sensor; else {after}")

    def observe(self, seq: int, reading: Reading | None, busy: bool, now: float) -> None:
        """The sensor's latest snapshot (its reading's ``seq``, and whether it is busy)."""
        fresh, self.seq, self.busy = seq > self.seq, seq, busy
        step = self.step
        if self.state is not State.RUNNING or self.in_flight or step is None:
            return
        if isinstance(step, Look) and seq > self.look_after and reading is not None:
            if reading.angles is None:
                self._end(State.FAILED, now, "the readings carry no angles")
                return
            self.angles[step.label] = _angles(reading.angles)
            self._next(now)
        elif isinstance(step, Heard) and seq > self.look_after and reading is not None:
            self._next(now)
        elif isinstance(step, Circle) and fresh and reading is not None:
            if reading.mag is None:
                self._end(State.FAILED, now, "the readings carry no mag values: this "
                          "sensor's polls must read the mag group")
                return
            self.circle.add(reading.mag.x, reading.mag.y)
            if len(self.circle.sectors) == SECTORS:
                self._next(now)
        else:
            self.tick(now)

    def user(self, choice: str, now: float) -> None:
        """The person's input: ``finish`` ends the circle where it stands."""
        if choice != "finish":
            raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"unknown input {choice!r}: the "
                                "one input is finish (end the circle)")
        if self.state is not State.RUNNING or not isinstance(self.step, Circle):
            raise RequestFailed(ErrorKind.BUSY, "there is no circle under way to finish")
        self._next(now)

    def cancel(self, now: float, force: bool = False) -> None:
        """The person's cancel (refused once a command that cannot be undone was
        sent), or the driver's (``force``)."""
        if self.state is not State.RUNNING:
            return
        if self.sent_any and not self.spec.cancellable_after_send and not force:
            raise RequestFailed(ErrorKind.BUSY, f"{self.spec.name} cannot be cancelled: "
                                "its command was sent to the sensor; it ends by itself")
        self._end(State.CANCELLED, now, "cancelled")
        self.cleaning = self.spec.cleanup is not None and self.sent_any

    def prompt(self) -> str:
        step = self.step
        if self.state is State.DONE:
            return "done" + (f": {' or '.join(self.spec.offers)} now, to keep it"
                             if self.spec.offers else "")
        if self.state is not State.RUNNING or step is None:
            return self.error or self.state.value
        return step.prompt or (f"sending {step.command}" if isinstance(step, Send) else "")

    def to_json(self, now: float) -> dict[str, Any]:
        """What a client sees (REST, the SSE events, the dashboard page)."""
        step = self.step
        countdown = None
        if self.state is State.RUNNING and isinstance(step, Countdown):
            countdown = round(max(0.0, self.step_began + step.seconds_of(self.args) - now), 1)
        quality = self.circle.quality()
        circle = "mag" in self.spec.name
        return {"procedure": self.spec.name, "state": self.state.value,
                "step": _step_name(step, self.args) if self.state is State.RUNNING else None,
                "steps": [_step_name(s, self.args) for s in self.spec.steps],
                "prompt": self.prompt(), "countdown_s": countdown,
                "elapsed_s": round((self.ended or now) - self.started, 1),
                "answers": self.answers, "angles": self.angles,
                "coverage_percent": self.circle.coverage_percent if circle else None,
                "points": self.circle.to_json() if circle else None,
                "quality": quality.to_json() if quality else None,
                "offers": list(self.spec.offers) if self.state is State.DONE else [],
                "error": self.error, "kind": self.kind.value if self.kind else None}


def _angles(angles: Angles) -> dict[str, float]:
    return {"pitch": angles.pitch, "roll": angles.roll, "yaw": angles.yaw}


def _step_name(step: Step | None, args: Args) -> str | None:
    """A step as clients see it: ``countdown``, ``mag_calibration start``, …"""
    match step:
        case Send(command=command, args_of=args_of) if command in CATALOGUE:
            action = (args_of(args) or {}).get("action")
            return f"{command} {action}" if action else command
        case Countdown():
            return "countdown"
        case UntilIdle():
            return "until_idle"
        case Circle():
            return "circle"
        case Look(label=label):
            return f"angles_{label}"
        case Reconfigure():
            return "config"
        case Heard():
            return "reading"
    return None
