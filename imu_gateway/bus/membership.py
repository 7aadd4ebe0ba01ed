"""A reload's sensors joining and leaving a running bus's schedule (docs/bus-master.md,
"A sensor added or removed by a reload"): the ``Schedule``'s part that a reload uses,
apart so that each stays readable.

A sensor added is polled from the moment it joins, in turn with the others, whose
state (learned timeouts, counters, a stream's phase) goes on untouched.  A sensor
removed gets no new job and the requests waiting for it fail; it leaves once nothing of
it is in flight: an exchange with it is never cut, and its answer never sent over.
"""

from __future__ import annotations

from ..config import BusConfig, SensorConfig
from ..errors import ErrorKind, RequestFailed
from .events import Job, Kind
from .jobs import JobQueue
from .line import Line
from .sensor_state import SensorState
from .timing import AnswerTimer


class Membership:
    """Adding and removing sensors (mixed into ``Schedule``, whose state it uses)."""

    config: BusConfig
    sensors: dict[str, SensorState]
    _line: list[SensorState]
    leaving: set[str]
    jobs: JobQueue
    line: Line
    port_open: bool
    stopping: bool

    def add(self, config: SensorConfig, now: float) -> None:
        """A sensor a reload added: polled from ``now`` on, in turn with the others,
        whose state (learned timeouts, counters, a stream's phase) goes on untouched."""
        if config.name in self.sensors:  # (still leaving: it comes back anew)
            self._forget(self.sensors[config.name])
        fixed = None if self.config.timeout_ms is None else self.config.timeout_ms / 1000
        s = SensorState(config, config.address, AnswerTimer(fixed))
        s.line = self._line
        self._line.append(s)
        s.stats.rate.started = s.next_due = now
        self.sensors[config.name] = s

    def remove(self, name: str, now: float) -> None:
        """A sensor a reload removed: it gets no new job, and the requests waiting for
        it fail.  It leaves once nothing of it is in flight (``sweep``, at
        ``take_events``): an exchange with it is never cut, and its answer never sent
        over.  A stream of it is stopped first, as at shutdown (the gateway set it up,
        or found it streaming unasked): its frames would meet the others' exchanges."""
        s = self.sensors[name]
        s.leaving = True
        self.leaving.add(name)
        removed = RequestFailed(ErrorKind.OFFLINE, f"{name} was removed from the config")
        self.jobs.drop(s, removed)
        current = self.jobs.current
        if current is not None and current.sensor is s and self.line.attempt is None \
                and not current.tries and not current.step:  # (not sent yet)
            self.jobs.current = None
            self.jobs.finish(current, error=removed)
            current = None
        setting_up = current is not None and current.kind is Kind.STREAM_START and \
            current.sensor is s
        if self.port_open and not self.stopping and \
                (s.streaming or s.stop_stream or setting_up):
            self.jobs.commands.append(Job(Kind.STREAM_STOP, s))

    def sweep(self) -> None:
        """The removed sensors with nothing in flight leave."""
        for name in list(self.leaving):
            s = self.sensors[name]
            if not self.jobs.holds(s) and \
                    (self.line.attempt is None or self.line.attempt.job.sensor is not s):
                self._forget(s)

    def _forget(self, s: SensorState) -> None:
        self.leaving.discard(s.name)
        del self.sensors[s.name]
        self._line.remove(s)
