"""The bus's schedule, sans-IO: what goes on the line next, and when.

``Schedule`` holds everything a bus master decides: the sensors' state, the queues
and priorities (``jobs``), back-off, online and offline, each sensor's learned answer
timing (``timing``), the evidence that a sensor streams unasked (``sensor_state``),
and the line's timing rules (``line``).  It has no clock, no port, no threads and no
asyncio.  Its driver (``master.BusMaster``) owns the port and does only this::

    schedule.start(now)                      # the driver begins (rates count from now)
    schedule.open(now)                       # the port is open
    request = schedule.next_request(now)     # None: nothing may go out now
    port.write(request.data)
    schedule.receive(data, at)               # bytes came in (at: when they came)
    schedule.handle_timer(now, pending)      # at schedule.next_wake(now); pending:
                                             # bytes the port holds, not yet received
    for event in schedule.take_events(): ... # readings, state changes, results, notes
    schedule.close(now, reason)              # the driver stops for good

The driver changes the schedule's state only through its methods
(tests/test_layering.py checks it).
"""

from __future__ import annotations

import logging
import math

from ..commands import Command
from ..config import BusConfig
from ..errors import ErrorKind, RequestFailed, unknown_sensor
from ..protocol.exchanges import (
    Answer,
    Exchange,
    Frame,
    ProtocolAdapter,
    char_time,
)
from ..stats import Counters
from .diagnosis import Diagnosis
from .events import (
    Event,
    Job,
    Kind,
    Note,
    Request,
    StateChange,
)
from .jobs import JobQueue
from .line import Due, Line, Place, stream_wait
from .membership import Membership
from .outcomes import Outcomes
from .sensor_state import STREAM_RETRY, SensorState, probe_times
from .timing import AnswerTimer


class Schedule(Membership):
    def __init__(self, config: BusConfig, adapter: ProtocolAdapter) -> None:
        self.config = config
        self.adapter = adapter
        fixed = None if config.timeout_ms is None else config.timeout_ms / 1000
        self.sensors = {s.name: SensorState(s, s.address, AnswerTimer(fixed))
                        for s in config.sensors}
        self._line = list(self.sensors.values())
        for state in self._line:
            state.line = self._line  # (its probes' spacing counts the line's dead sensors)
        self.leaving: set[str] = set()  # removed by a reload, something of theirs in flight
        self.stats = Counters()
        self.started = 0.0
        self.port_open = False
        self.stopping = False
        self._events: list[Event] = []
        self.jobs = JobQueue(self._events.append, self.stats)
        self.line = Line(adapter, config.baudrate, self.stats, self._frame)
        self.diagnosis = Diagnosis(config.protocol, config.port)
        self.outcomes = Outcomes(config, adapter, self.sensors, self.jobs, self.line,
                                 self.stats, self._events.append, self.diagnosis)

    @property
    def baud(self) -> int:
        """The line's rate now (a command may have moved it)."""
        return self.line.baud

    def start(self, now: float) -> None:
        """The driver begins: the bus's and its sensors' rates count from ``now``."""
        self.started = self.stats.rate.started = now
        for s in self.sensors.values():
            s.stats.rate.started = now

    def trace(self, on: bool) -> None:
        """A ``Trace`` event for every exchange from now on, or none (its driver's
        log or traffic monitors want them, or nobody does)."""
        self.outcomes.tracing = on

    def count_reading(self, name: str, at: float) -> None:
        """A reading of ``name`` reached the cache (the driver normalises answers)."""
        stats = self.sensors[name].stats
        stats.readings += 1
        stats.rate.add(at)

    def take_events(self) -> list[Event]:
        """What happened since last asked (the removed sensors with nothing in flight
        leave now: ``sweep``)."""
        if self.leaving:
            self.sweep()
        events = self._events[:]
        self._events.clear()  # the same list: the job queue appends to it too
        return events

    # ------------------------------------------------------------ requests from users

    def refusal(self, name: str, queued: bool = True) -> RequestFailed | None:
        """Why a request for ``name`` cannot be taken now (it is answered at once).

        An offline sensor is not asked on demand: that would undo its back-off and
        hand the line to a dead address (it is still retried in the background)."""
        s = self.sensors.get(name)
        if s is None:
            return unknown_sensor(name)
        if s.leaving:
            return RequestFailed(ErrorKind.OFFLINE, f"{name} was removed from the config")
        if self.stopping:
            return RequestFailed(ErrorKind.OFFLINE, "the gateway is stopping")
        if not self.port_open:
            return RequestFailed(ErrorKind.OFFLINE, f"the port of bus {self.config.name} "
                                 f"({self.config.port}) is not open")
        if s.online is False:
            return RequestFailed(ErrorKind.OFFLINE, f"{s.name} is offline (it is retried in "
                                 f"the background; {s.failures} failed exchanges so far)")
        return self.jobs.full(s) if queued else None

    def command(self, name: str, command: Command) -> Job:
        """Queue a validated command (check ``refusal`` first)."""
        return self.jobs.command(self.sensors[name], command)

    def passthrough(self, name: str, exchange: Exchange) -> Job:
        return self.jobs.passthrough(self.sensors[name], exchange)

    def read(self, name: str) -> tuple[Job, bool]:
        """An on-demand read of ``name``; concurrent askers share one.  Returns the job
        and whether it is new.  A streaming sensor's next frame serves it."""
        return self.jobs.read(self.sensors[name])

    def queue_depth(self) -> int:
        return len(self.jobs)

    # ------------------------------------------------------------ the port

    def open(self, now: float) -> None:
        """The port is open (again): start afresh."""
        self.port_open = True
        self.line.reset(now)
        for s in self.sensors.values():
            s.next_due = now
            s.stream_ended()
            s.stream_retry_at = min(s.stream_retry_at, now)  # (inf: a rate it cannot do)
            s.timer.backoff = 0

    def lost(self, now: float, reason: str) -> None:
        """The port is gone (or could not be opened): everything fails as offline."""
        if self.line.attempt is not None:
            self.line.close(self.line.attempt, now, answered=False)
        if self.port_open:
            self.stats.errors["port_lost"] += 1
        self.port_open = False
        if self.jobs.current is not None:
            self.outcomes.fail_job(self.jobs.current, now, "port_lost",
                                   f"bus {self.config.name}: {reason}")
        for s in self.sensors.values():
            # What was seen before the loss proves nothing about what is there after it.
            s.stop_stream = False
            s.evidence.clear()
            if s.online is not False or s.streaming:
                s.online = False
                s.stream_ended()
                self._events.append(StateChange(s.name, online=False, streaming=False))
        self.jobs.fail_all(ErrorKind.OFFLINE, f"the port of bus {self.config.name} is not open")
        self.jobs.stops.clear()

    def stop(self, now: float) -> None:
        """Finish the exchange in flight, stop every stream, then be ``finished``."""
        if self.stopping:
            return
        self.stopping = True
        self.jobs.fail_all(ErrorKind.OFFLINE, "the gateway is stopping")
        if not self.port_open:
            return
        current = self.jobs.current
        for s in self.sensors.values():
            setting_up = current is not None and current.kind is Kind.STREAM_START and \
                current.sensor is s
            if s.streaming or s.stop_stream or setting_up:
                # Leave the line quiet for the next owner: stop the auto-output (also of
                # a stream being set up now, or found streaming unasked).
                self.jobs.stops.append(Job(Kind.STREAM_STOP, s))

    def abort(self, now: float, message: str) -> None:
        """Drop the exchange in flight and answer its job as failed (an internal error,
        or the bus thread ending); it does not count against the sensor."""
        if self.line.attempt is not None:
            self.line.close(self.line.attempt, now, answered=False)
        self.line.flush(now)
        if self.jobs.current is not None:
            self.outcomes.fail_job(self.jobs.current, now, "internal", message)

    def close(self, now: float, reason: str) -> None:
        """The driver closed the port for good: the exchange in flight and every job
        waiting fail (as offline, not against their sensors)."""
        self.port_open = False
        self.abort(now, reason)
        self.jobs.fail_all(ErrorKind.OFFLINE, reason)

    @property
    def finished(self) -> bool:
        return self.stopping and self.jobs.current is None and \
            (not self.jobs.stops or not self.port_open)

    # ------------------------------------------------------------ what goes next

    def next_request(self, now: float, pending: int = 0) -> Request | None:
        """The request to write now, or None (see ``next_wake``).  ``pending``: bytes the
        port holds that ``receive`` has not had yet."""
        if not self.port_open or self.line.attempt is not None or \
                now < self.line.free_at(now, pending):
            return None
        job = self.jobs.current
        if job is not None and job.kind in (Kind.POLL, Kind.SETTINGS) and not job.tries \
                and self.jobs.ready(self.stopping):
            # a poll (or settings read) not sent yet gives way to a command
            job = self.jobs.current = None
        if job is None:
            job = self.jobs.current = self.jobs.pick(
                now, (s for s in self.sensors.values() if not s.leaving), self.stopping)
            if job is None:
                return None
            if not self.jobs.begin(job, self.adapter):
                self.jobs.current = None
                return self.next_request(now, pending)
        exchange = job.plan[job.step]
        place = self._stream_place(job, exchange, now)
        if place.at > now:
            if job.blocked_since is None:
                job.blocked_since = now
            return None
        job.blocked_since = None
        s = job.sensor
        timeout, hold = (s.timer.rto, s.timer.hold) if s.online else \
            probe_times(s, self.sensors.values())
        # A retry, or a sensor that is not answering as it did, is watched for at once.
        early = s.timer.look_after() if s.online and not job.tries else 0.0
        return self.line.send(job, exchange, now, timeout, hold, place, early)

    def written(self, at: float) -> None:
        """The request ``next_request`` handed out was written by ``at``."""
        self.line.written(at)

    def withdraw(self) -> None:
        """The request ``next_request`` handed out was not written by its ``latest``."""
        self.line.withdraw()

    def next_wake(self, now: float, pending: int = 0) -> float:
        """When ``handle_timer`` or ``next_request`` next has something to do."""
        a = self.line.attempt
        if a is not None:
            return max(a.give_up, a.deadline) if a.overdue else a.deadline
        if not self.port_open and not self.stopping:
            return now  # the driver reopens it
        times = [now + 1.0]  # housekeeping: busy periods and streams that end
        work = [now] if self.jobs.current or self.jobs.ready(self.stopping) else []
        for s in self.sensors.values():
            if s.leaving:
                continue  # (its stream's stop is a command)
            if s.busy_until > now:
                times.append(s.busy_until)
                if not s.read_while_busy:
                    continue
            if s.streaming:
                times.append(s.last_stream + s.stream_timeout)
                if s.online is True and s.settings_at < math.inf:  # (``settings_due``)
                    work.append(max(s.settings_at, s.busy_until))
            else:
                work.append(s.next_due)
            if (s.config.stream_hz and not s.streaming) or s.stop_stream:
                work.append(s.stream_retry_at)
        if work and self.port_open:
            ready = max(min(work), self.line.free_at(now, pending))
            if self.jobs.current is not None:
                ready = max(ready, self._stream_place(
                    self.jobs.current, self.jobs.current.plan[self.jobs.current.step], now)[0])
            times.append(ready)
        return min(times)

    def _stream_place(self, job: Job, exchange: Exchange, now: float) -> Place:
        """When ``exchange`` may go next to the line's streaming sensor, and the latest it
        may then still be written: with its sensor's answer latency as learned
        (``line.stream_wait``).  After a stream is set up, nothing goes until its first
        frame has set the phase."""
        streamer = next((t for t in self.sensors.values() if t.streaming), None)
        if streamer is None:
            return Place(now, math.inf, "")
        period = 1 / streamer.config.stream_hz
        if not streamer.stream_frames and now < streamer.last_stream + 2 * period:
            return Place(streamer.last_stream + 2 * period, 0.0, "the stream's first frame")
        frame = streamer.poll(self.adapter).answer_bytes * char_time(self.baud)
        needs = self.line.wire(exchange) + self.line.gap + job.sensor.timer.expected()
        last_end = streamer.frame_end_before(now)  # in phase: not as late as it was seen
        # Someone waits for anything but a poll: those must get their place in the end.
        # A poll can wait (its miss is counted): it never goes where it does not fit.
        waited = 0.0 if job.blocked_since is None or job.kind is Kind.POLL else \
            now - job.blocked_since
        return stream_wait(now, needs, last_end, period, frame, waited)

    # ------------------------------------------------------------ what comes in

    def receive(self, data: bytes, at: float) -> None:
        """Bytes from the line; ``at``: when the last of them came in."""
        self.diagnosis.received(data)
        self.line.receive(data, at)  # each whole frame goes to ``outcomes.frame``

    # ------------------------------------------------------------ timers

    def needs_pending(self) -> bool:
        """Whether the bytes the port holds (``pending``) matter to ``handle_timer``,
        ``next_request`` and ``next_wake`` now: with an attempt in flight, half a frame
        in hand, or a sensor streaming.  Otherwise they read it not at all, and the
        driver need not ask the port."""
        return self.line.attempt is not None or bool(self.line.framer.pending) or \
            any(s.streaming for s in self.sensors.values())

    def handle_timer(self, now: float, pending: int = 0) -> None:
        """Deadlines, streams that stopped, busy periods that ended.  ``pending``: bytes
        the port holds that ``receive`` has not had yet (a busy machine's timer fires
        late; the answer may be in already)."""
        a = self.line.attempt
        due = self.line.check(now, pending)
        if a is not None and due is Due.SENT:
            self.outcomes.answered(a, Answer({}), now)
        elif a is not None and due is Due.FAILED:
            self.outcomes.timed_out(a, now)
        for s in self.sensors.values():
            # (frames may be in the port, not yet received, on a busy machine)
            if s.streaming and now - s.last_stream > s.stream_timeout and not pending:
                s.stream_ended()
                s.stream_retry_at = now + STREAM_RETRY
                s.next_due = now
                self._events.append(StateChange(s.name, streaming=False))
                self._events.append(Note(logging.WARNING, f"sensor {s.name}: its stream "
                                         "stopped; polling it"))
            if s.busy_until and now >= s.busy_until:
                s.busy_until = 0.0
                self._events.append(StateChange(s.name, busy=False))

    def _frame(self, frame: Frame, at: float) -> None:
        self.outcomes.frame(frame, at)
