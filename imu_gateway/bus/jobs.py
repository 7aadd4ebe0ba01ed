"""What waits for the line, and what goes next, sans-IO.

Next is, in this order:

1. commands (and Modbus pass-through requests), first come first served;
2. a stream set-up for a sensor with ``stream_hz`` that is not streaming;
3. a stop for a sensor found streaming unasked (on evidence only, see
   ``sensor_state``);
4. on-demand reads, one per sensor however many ask;
5. the settings read (``read_settings``) of a sensor back from offline, at its poll's
   turn (a streaming one's: at once), once;
6. polls: the due sensor that waited longest first.

While stopping, only the stops of the streams go out.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable, Iterable

from ..commands import Command, CommandResult
from ..errors import ErrorKind, RequestFailed
from ..protocol.errors import UsageError
from ..protocol.exchanges import Exchange, ProtocolAdapter, Unsupported
from ..stats import Counters
from .events import Event, Finished, Job, Kind, Note, Outcome
from .sensor_state import STREAM_RETRY, SensorState

MAX_QUEUED_PER_SENSOR = 16  # commands waiting for one sensor before more are refused (busy)
#: what the bus sends by itself to learn a sensor's settings anew
READ_SETTINGS = Command("read_settings")


class JobQueue:
    def __init__(self, emit: Callable[[Event], None], stats: Counters) -> None:
        self.emit = emit
        self.stats = stats  # the bus's
        self.commands: deque[Job] = deque()
        self.reads: dict[str, Job] = {}
        self.stops: deque[Job] = deque()  # streams to stop on shutdown
        self.current: Job | None = None  # the job whose exchanges are going out

    def __len__(self) -> int:
        return len(self.commands) + len(self.reads)

    def __bool__(self) -> bool:
        return bool(self.commands or self.reads or self.stops)

    def ready(self, stopping: bool) -> bool:
        """Is a queued job ready to go as soon as the line is free?  (A read of a
        streaming sensor is not: its next frame serves it.)"""
        if stopping:
            return bool(self.stops)
        return bool(self.commands) or any(
            not j.sensor.streaming and not j.started for j in self.reads.values())

    def full(self, s: SensorState) -> RequestFailed | None:
        if sum(j.sensor is s for j in self.commands) >= MAX_QUEUED_PER_SENSOR:
            return RequestFailed(ErrorKind.BUSY, f"{MAX_QUEUED_PER_SENSOR} requests for "
                                 f"{s.name} are already waiting")
        return None

    def command(self, s: SensorState, command: Command) -> Job:
        job = Job(Kind.COMMAND, s, command=command)
        self.commands.append(job)
        return job

    def passthrough(self, s: SensorState, exchange: Exchange) -> Job:
        job = Job(Kind.PASSTHROUGH, s, plan=[exchange])
        self.commands.append(job)
        return job

    def read(self, s: SensorState) -> tuple[Job, bool]:
        """The on-demand read of ``s`` (shared), and whether it is new."""
        job = self.reads.get(s.name)
        if job is not None:
            return job, False
        job = self.reads[s.name] = Job(Kind.READ, s)
        return job, True

    def fail_all(self, kind: ErrorKind, message: str) -> None:
        while self.commands:
            self.finish(self.commands.popleft(), error=RequestFailed(kind, message))
        for job in list(self.reads.values()):
            self.finish(job, error=RequestFailed(kind, message))

    def drop(self, s: SensorState, error: RequestFailed) -> None:
        """Every job of ``s`` that waits (not the one going out) fails with ``error``."""
        for job in [j for j in self.commands if j.sensor is s]:
            self.commands.remove(job)
            self.finish(job, error=error)
        read = self.reads.get(s.name)
        if read is not None and read is not self.current:
            self.finish(read, error=error)

    def holds(self, s: SensorState) -> bool:
        """Is a job of ``s`` going out, or waiting?"""
        return (self.current is not None and self.current.sensor is s) or \
            any(j.sensor is s for j in self.commands) or s.name in self.reads

    def finish(self, job: Job, outcome: Outcome = None,
               error: RequestFailed | None = None) -> None:
        """The job is over: whoever waits for it is told (a command always gets a
        ``CommandResult``; a read or a pass-through gets its outcome or ``error``)."""
        if self.reads.get(job.sensor.name) is job:
            del self.reads[job.sensor.name]
        if job.kind in (Kind.POLL, Kind.STREAM_START, Kind.STREAM_STOP):
            return  # nobody waits for these (SETTINGS: the driver learns from it)
        if error is not None and job.command is not None:
            outcome = CommandResult.failed(job.sensor.name, job.command.name, error)
            error = None
        self.emit(Finished(job, outcome, error))

    def pick(self, now: float, sensors: Iterable[SensorState], stopping: bool) -> Job | None:
        if stopping:
            return self.stops.popleft() if self.stops else None
        while self.commands:
            job = self.commands.popleft()
            if job.sensor.busy_until <= now:
                return job
            self.finish(job, error=RequestFailed(ErrorKind.BUSY, f"{job.sensor.name} is busy "
                        f"for another {job.sensor.busy_until - now:.1f} s (save or "
                        "calibration)"))
        sensors = list(sensors)
        for s in sensors:
            if s.wants_stream(now):
                return Job(Kind.STREAM_START, s)
            if s.stop_stream and now >= s.stream_retry_at:
                return self._stop_unasked(s, now)
        for name, job in list(self.reads.items()):
            if job.sensor.busy_until > now and not job.sensor.read_while_busy:
                self.finish(job, error=RequestFailed(ErrorKind.BUSY, f"{name} is busy (save "
                                                     "or calibration)"))
            elif not job.sensor.streaming and not job.started:
                return job  # stays listed until answered, for later askers
        for s in sensors:
            if s.settings_due(now):
                return Job(Kind.SETTINGS, s, command=READ_SETTINGS)
        due = [s for s in sensors if s.due(now)]
        if due:
            return Job(Kind.POLL, min(due, key=lambda s: (s.next_due, s.last_served)))
        return None

    def _stop_unasked(self, s: SensorState, now: float) -> Job:
        s.stop_stream, s.stream_retry_at = False, now + STREAM_RETRY
        s.stats.stream_stops += 1
        self.stats.stream_stops += 1
        self.emit(Note(logging.WARNING, f"sensor {s.name}: streams though stream_hz is 0 "
                       "(steady frames nobody asked for); stopping it"))
        return Job(Kind.STREAM_STOP, s)

    def begin(self, job: Job, adapter: ProtocolAdapter) -> bool:
        """Make the job's exchanges; False (and finished) when it cannot have any."""
        s, series = job.sensor, job.sensor.config.series
        job.started = True
        try:
            match job.kind:
                case Kind.POLL | Kind.READ:
                    job.plan = [s.poll(adapter)]
                case Kind.STREAM_START:
                    job.plan = adapter.stream_start(series, s.address, s.config.stream_hz)
                case Kind.STREAM_STOP:
                    job.plan = adapter.stream_stop(series, s.address)
                case Kind.COMMAND | Kind.SETTINGS:
                    assert job.command is not None
                    job.plan = adapter.command(series, s.address, job.command.name,
                                               job.command.args)
        except UsageError as exc:  # Unsupported, or a value the protocol cannot carry
            if job.kind is Kind.STREAM_START:
                self.emit(Note(logging.ERROR, f"sensor {s.name}: cannot stream at "
                               f"{s.config.stream_hz} Hz: {exc}"))
                s.stream_retry_at = float("inf")
            if job.kind is Kind.SETTINGS:
                s.settings_at = math.inf  # (every series has it: never, in fact)
            kind = ErrorKind.UNSUPPORTED if isinstance(exc, Unsupported) else \
                ErrorKind.BAD_ARGUMENTS
            self.finish(job, error=RequestFailed(kind, str(exc)))
            return False
        return True
