"""What a bus master counts, and the frozen views of it the front ends read.

The counters belong to a bus master and change on its thread.  ``SensorStats`` and
``BusStats`` are frozen snapshots of them, made when a front end asks; the front ends
read only those (they never import the bus).
"""

from __future__ import annotations

import dataclasses
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

RATE_WINDOW = 5.0  # seconds over which achieved rates are measured

#: The kinds of failed exchange a bus counts (``Counters.errors``' keys; what
#: docs/troubleshooting.md explains).  Metrics show each from 0, so that a rate sees
#: the first one.
ERROR_KINDS = ("timeout", "bad_frame", "unexpected_frame", "refused", "port_lost")


@dataclass(slots=True)
class RateMeter:
    """Events per second over the last ``RATE_WINDOW`` seconds (or since ``started``)."""

    started: float = 0.0
    times: deque[float] = field(default_factory=lambda: deque(maxlen=65536))

    def add(self, at: float) -> None:
        self.times.append(at)

    def per_second(self, now: float) -> float:
        while self.times and self.times[0] < now - RATE_WINDOW:
            self.times.popleft()
        span = min(RATE_WINDOW, now - self.started)
        return len(self.times) / span if span > 0 else 0.0


@dataclass(slots=True)
class Counters:
    """One sensor's, or one bus's, running totals."""

    transactions: int = 0
    readings: int = 0
    missed_polls: int = 0
    late_answers: int = 0  # answers that came after their timeout, and were used
    #: answers in sooner than request, gap and answer could cross the wire, and used
    early_answers: int = 0
    stream_stops: int = 0  # stops sent to a sensor found streaming unasked
    #: (a bus's) requests written too late, next to a stream, for their exchange to
    #: end before the stream's next frame: each may have met it (``Line.written``)
    late_writes: int = 0
    busy_time: float = 0.0  # the line was ours: request, answer delay, answer, gaps
    wire_time: float = 0.0  # the bytes of the exchanges done, at the wire's rate
    errors: Counter[str] = field(default_factory=Counter)
    rate: RateMeter = field(default_factory=RateMeter)


def ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1000, 2)


@dataclass(frozen=True, slots=True)
class Trace:
    """One exchange for the frame trace (made by the bus, shown by the log and by
    REST's traffic monitor): what went out, what came in, how long from
    the request's start to the last byte in, and the outcome ("ok", "late",
    "timeout", "garbled", "refused", …)."""

    sensor: str
    tx: bytes
    rx: bytes
    took: float
    outcome: str
    placed: str = ""  # next to a stream: the rule that placed the request
    at: float = 0.0  # when it ended (time.monotonic() on the bus thread)


@dataclass(frozen=True, slots=True)
class SensorStats:
    """One sensor as its bus master sees it."""

    address: int  # the live one (after a set_address too)
    online: bool
    streaming: bool
    transactions: int
    readings: int
    errors: Mapping[str, int]
    missed_polls: int
    late_answers: int
    early_answers: int
    stream_stops: int
    bus_share: float  # of the bus's time since start
    requested_hz: float
    achieved_hz: float
    latency_ms: float | None  # smoothed answer latency; None before the first answer
    latency_dev_ms: float | None  # its mean deviation
    timeout_ms: float  # what the next attempt waits beyond the wire time

    def as_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "errors": dict(self.errors)}


@dataclass(frozen=True, slots=True)
class BusStats:
    """One serial line."""

    name: str
    port: str
    baudrate: int
    protocol: str
    port_open: bool
    transactions: int
    errors: Mapping[str, int]
    late_answers: int
    early_answers: int
    late_writes: int
    transactions_per_s: float
    utilisation: float  # time in exchanges ÷ elapsed
    busy_ms: int
    wire_utilisation: float  # the model: bytes and RTU gaps only
    queue_depth: int

    def as_dict(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "errors": dict(self.errors)}


#: A front end's own counters, by name (``clients``, ``requests``, ``connected`` …).
FrontendCounts = dict[str, int | bool]


def share(part: float, elapsed: float) -> float:
    return round(part / elapsed, 4) if elapsed > 0 else 0.0


__all__ = ["ERROR_KINDS", "BusStats", "Counters", "FrontendCounts", "RateMeter", "SensorStats",
           "ms", "share"]
