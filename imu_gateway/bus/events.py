"""What the schedule hands its driver: jobs, the request to write, and events.

Events say what happened, in order; the driver carries them out (the cache, the
futures of whoever asked, the log).  None of them needs the driver to answer.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

from ..commands import Command, CommandResult
from ..errors import RequestFailed
from ..protocol.exchanges import Answer, Exchange
from ..stats import Trace as Trace  # (defined there: the front ends read it)
from .sensor_state import SensorState


class Kind(enum.Enum):
    """What a job is for.  Who waits for it: COMMAND, PASSTHROUGH and READ (and the
    driver, for SETTINGS: what the answer shows goes to the cache)."""

    COMMAND = "command"
    PASSTHROUGH = "pass-through"
    STREAM_START = "stream set-up"
    STREAM_STOP = "stream stop"
    READ = "on-demand read"
    SETTINGS = "settings read"  # read_settings, by the bus itself (a sensor back from offline)
    POLL = "poll"


@dataclass(eq=False, slots=True)
class Job:
    """Work for one sensor: one or more exchanges, in order."""

    kind: Kind
    sensor: SensorState
    command: Command | None = None
    plan: list[Exchange] = field(default_factory=list)
    step: int = 0  # the exchange now due
    tries: int = 0  # attempts of that exchange so far
    values: dict[str, Any] = field(default_factory=dict)  # the answers' values, merged
    started: bool = False
    blocked_since: float | None = None  # waiting for a place next to a stream since


@dataclass(slots=True)
class Attempt:
    """One request on the line, waiting for its answer."""

    job: Job
    exchange: Exchange
    sent: float
    wire: float  # request, answer and the gap between them, at the line's rate
    deadline: float  # the answer is due by then: sent + wire + the sensor's timeout
    give_up: float  # the line is held for a late answer until then
    started: float  # the silent gap before the request began (busy time counts it)
    garbage: int  # the framer's garbage count when it was sent (noise vs silence)
    overdue: bool = False
    tx_end_before: float = 0.0  # the line's last request end before this one
    #: the write took long enough that when the request left is not known: its
    #: answer measures nothing (``Line.written``)
    untimed: bool = False
    #: the bus looked for the answer only at its usual time (``Request.look_after``):
    #: found whole then, it too measures nothing
    looked: bool = False
    #: why it went when it did, next to a stream (``line.stream_wait``)
    placed: str = ""
    #: next to a stream, the last moment it could go and end before the stream's next
    #: frame, if that frame comes on time (its place's latest, and the room kept)
    clear_by: float = math.inf


@dataclass(frozen=True, slots=True)
class Request:
    """Bytes to write now; ``expect`` is the answer's length (0: none comes).  Not
    written by ``latest`` (the driver was kept from it), it must be withdrawn."""

    data: bytes
    expect: int
    latest: float = math.inf
    #: the whole answer cannot be in sooner than this many seconds after the write:
    #: the port need not be watched until then (0: watch it at once)
    look_after: float = 0.0


@dataclass(frozen=True, slots=True)
class Publish:
    """A sensor's answer or stream frame: a reading for the cache."""

    sensor: str
    answer: Answer
    at: float


@dataclass(frozen=True, slots=True)
class StateChange:
    """What the cache shows of a sensor; None: unchanged."""

    sensor: str
    online: bool | None = None
    busy: bool | None = None
    streaming: bool | None = None


@dataclass(frozen=True, slots=True)
class ErrorCounted:
    sensor: str


#: What a job someone waits for ends with: a command's result (success or not), a
#: pass-through's answer PDU, or None (a read: its reading is in the cache by then).
Outcome = CommandResult | bytes | None


@dataclass(frozen=True, slots=True)
class Finished:
    """A job someone waits for is done: its ``outcome``, or ``error``."""

    job: Job
    outcome: Outcome
    error: RequestFailed | None = None


@dataclass(frozen=True, slots=True)
class Note:
    """A line for the log (``level`` as in ``logging``)."""

    level: int
    text: str


Event = Publish | StateChange | ErrorCounted | Finished | Note | Trace
