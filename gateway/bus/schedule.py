"""The bus's schedule, sans-IO: what goes on the line next, and when.

``Schedule`` holds everything a bus master decides: the sensors' state, the queues,
priorities, back-off, online and offline, each sensor's learned answer timing, the
evidence that a sensor streams unasked, and the line's timing rules.  It has no
clock, no port, no threads and no asyncio.  Its driver (``master.BusMaster``) owns
the port and does only this::

    schedule.open(now)                       # the port is open
    request = schedule.next_request(now)     # None: nothing may go out now
    port.write(request.data)
    schedule.receive(data, at)               # bytes came in (at: when they came)
    schedule.handle_timer(now, pending)      # at schedule.next_wake(now); pending:
                                             # bytes the port holds, not yet received
    for event in schedule.take_events(): ... # readings, state changes, results, notes

The rules, each in one place:

* **What goes next** (``_pick``): commands (and pass-through) first come first served;
  stream set-up; a stop for a sensor found streaming unasked; on-demand reads (one per
  sensor however many ask); then polls, the due sensor that waited longest first.
* **When a request may go** (``_line_free_at``, ``_stream_allows``): never while an
  exchange is in flight, including the time its answer may still come late; after
  noise or half a frame, only once the line has been quiet 3.5 characters (at least
  1 ms); after the protocol's gap; next to a streaming sensor, only if the exchange
  fits before its next frame.
* **Timeouts** (``handle_timer``): an attempt's answer is due by its wire time plus the
  sensor's learned timeout (``timing.AnswerTimer``).  Past that it is *overdue*, but
  the line stays held for another timeout: an answer then is recognised as the late
  answer it is, used, and counted.  Only after that is the attempt a failure.  A
  timer that fires while the port holds unread bytes waits for them first.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from typing import Any

from ..commands import Command, CommandError, CommandResult, ErrorKind
from ..config import BusConfig
from ..protocol.errors import UsageError
from ..protocol.exchanges import (
    GYRO_CAL_SECONDS,
    Answer,
    Effect,
    Exchange,
    ProtocolAdapter,
    Unsupported,
    char_time,
)
from ..stats import Counters
from .events import (
    Attempt,
    ErrorCounted,
    Event,
    Finished,
    Job,
    Kind,
    Note,
    Publish,
    Request,
    StateChange,
)
from .sensor_state import STREAM_RETRY, SensorState
from .timing import AnswerTimer

MAX_QUEUED_PER_SENSOR = 16  # commands waiting for one sensor before more are refused (busy)
MIN_QUIET = 0.001  # after noise, the line must have been quiet this long
#: An attempt overdue with bytes still arriving is waited for this much longer at most.
ARRIVING_GRACE = 0.05


def stream_wait(now: float, needs: float, last_end: float, period: float,
                frame: float) -> float:
    """When an exchange of ``needs`` seconds may start next to a stream whose frames
    take ``frame`` seconds every ``period``, the last one seen ending at ``last_end``.

    The stream keeps its phase: a frame that was lost (garbled, or dropped by the
    port) does not make the next one come at another time, so the frames are expected
    at ``last_end + k·period``.  A frame due but not seen yet is given half a period
    to arrive (a busy machine, or a sensor's own clock, makes frames late) before it
    is taken for lost and the line is used."""
    margin = min(0.02, period / 10) + MIN_QUIET  # the frames' own timing wobbles
    k = max(1, math.ceil((now - last_end) / period))
    due = last_end + (k - 1) * period  # the latest frame that should have ended by now
    if k > 1 and now < due + period / 2:
        return due + period / 2  # it may still be coming in
    next_end = due + period
    if now + needs + margin <= next_end - frame:
        return now  # fits before the next frame
    if needs + margin > period - frame and now - due <= margin and k == 1:
        return now  # never fits a pause: right after a frame is the least harm
    return next_end  # in the pause after the next frame (its arrival wakes us sooner)


class Schedule:
    def __init__(self, config: BusConfig, adapter: ProtocolAdapter) -> None:
        self.config = config
        self.adapter = adapter
        self.baud = config.baudrate
        fixed = None if config.timeout_ms is None else config.timeout_ms / 1000
        self.sensors = {s.name: SensorState(s, s.address, AnswerTimer(fixed))
                        for s in config.sensors}
        self.stats = Counters()
        self.started = 0.0
        self.port_open = False
        self.stopping = False
        self._framer = adapter.new_framer()
        self._commands: deque[Job] = deque()
        self._reads: dict[str, Job] = {}
        self._stops: deque[Job] = deque()  # streams to stop on shutdown
        self._job: Job | None = None
        self._attempt: Attempt | None = None
        self._events: list[Event] = []
        self._last_rx = 0.0
        self._last_tx_end = 0.0
        self._busy_end = 0.0
        self._dirty = False

    # ------------------------------------------------------------ requests from users

    def refusal(self, name: str, queued: bool = True) -> CommandError | None:
        """Why a request for ``name`` cannot be taken now (it is answered at once).

        An offline sensor is not asked on demand: that would undo its back-off and
        hand the line to a dead address (it is still retried in the background)."""
        s = self.sensors[name]
        if self.stopping:
            return CommandError(ErrorKind.OFFLINE, "the gateway is stopping")
        if not self.port_open:
            return CommandError(ErrorKind.OFFLINE, f"the port of bus {self.config.name} "
                                f"({self.config.port}) is not open")
        if s.online is False:
            return CommandError(ErrorKind.OFFLINE, f"{s.name} is offline (it is retried in "
                                f"the background; {s.failures} failed exchanges so far)")
        if queued and sum(j.sensor is s for j in self._commands) >= MAX_QUEUED_PER_SENSOR:
            return CommandError(ErrorKind.BUSY, f"{MAX_QUEUED_PER_SENSOR} requests for "
                                f"{s.name} are already waiting")
        return None

    def command(self, name: str, command: Command) -> Job:
        """Queue a validated command (check ``refusal`` first)."""
        job = Job(Kind.COMMAND, self.sensors[name], command=command)
        self._commands.append(job)
        return job

    def passthrough(self, name: str, exchange: Exchange) -> Job:
        job = Job(Kind.PASSTHROUGH, self.sensors[name], plan=[exchange])
        self._commands.append(job)
        return job

    def read(self, name: str) -> tuple[Job, bool]:
        """An on-demand read of ``name``; concurrent askers share one.  Returns the job
        and whether it is new.  A streaming sensor's next frame serves it."""
        job = self._reads.get(name)
        if job is not None:
            return job, False
        job = self._reads[name] = Job(Kind.READ, self.sensors[name])
        return job, True

    def queue_depth(self) -> int:
        return len(self._commands) + len(self._reads)

    def take_events(self) -> list[Event]:
        events, self._events = self._events, []
        return events

    # ------------------------------------------------------------ the port

    def open(self, now: float) -> None:
        """The port is open (again): start afresh."""
        self.port_open = True
        self._framer = self.adapter.new_framer()
        self._dirty = False
        self._last_rx = self._last_tx_end = now
        for s in self.sensors.values():
            s.next_due, s.streaming, s.stream_retry_at = now, False, now

    def lost(self, now: float, reason: str) -> None:
        """The port is gone (or could not be opened): everything fails as offline."""
        if self._attempt is not None:
            self._account(self._attempt, now)
            self._attempt = None
        if self.port_open:
            self.stats.errors["port_lost"] += 1
        self.port_open = False
        if self._job is not None:
            self._fail_job(self._job, now, "port_lost", f"bus {self.config.name}: {reason}")
        for s in self.sensors.values():
            if s.online is not False or s.streaming:
                s.online, s.streaming = False, False
                self._events.append(StateChange(s.name, online=False, streaming=False))
        self.fail_pending(ErrorKind.OFFLINE, f"the port of bus {self.config.name} is not open")
        self._stops.clear()

    def fail_pending(self, kind: ErrorKind, message: str) -> None:
        while self._commands:
            self._finish(self._commands.popleft(), error=CommandError(kind, message))
        for job in list(self._reads.values()):
            self._finish(job, error=CommandError(kind, message))

    def stop(self, now: float) -> None:
        """Finish the exchange in flight, stop every stream, then be ``finished``."""
        if self.stopping:
            return
        self.stopping = True
        self.fail_pending(ErrorKind.OFFLINE, "the gateway is stopping")
        if self.port_open:
            for s in self.sensors.values():
                if s.streaming:
                    # Leave the line quiet for the next owner: stop the auto-output.
                    self._stops.append(Job(Kind.STREAM_STOP, s))

    @property
    def finished(self) -> bool:
        return self.stopping and self._job is None and (not self._stops or not self.port_open)

    # ------------------------------------------------------------ what goes next

    def next_request(self, now: float) -> Request | None:
        """The request to write now, or None (see ``next_wake``)."""
        if not self.port_open or self._attempt is not None or now < self._line_free_at(now):
            return None
        job = self._job
        if job is None:
            job = self._job = self._pick(now)
            if job is None:
                return None
            if not self._begin(job, now):
                return self.next_request(now)
        exchange = job.plan[job.step]
        if self._stream_allows_at(job.sensor, exchange, now) > now:
            return None
        return self._send(job, exchange, now)

    def next_wake(self, now: float) -> float:
        """When ``handle_timer`` or ``next_request`` next has something to do."""
        a = self._attempt
        if a is not None:
            return a.give_up if a.overdue else a.deadline
        times = [now + 1.0]  # housekeeping: busy periods and streams that end
        work = [now] if self._job or self._commands or self._reads or self._stops else []
        for s in self.sensors.values():
            if s.busy_until > now:
                times.append(s.busy_until)
                continue
            if s.streaming:
                times.append(s.last_stream + s.stream_timeout)
            else:
                work.append(s.next_due)
            if (s.config.stream_hz and not s.streaming) or s.stop_stream:
                work.append(s.stream_retry_at)
        if work and self.port_open:
            ready = max(min(work), self._line_free_at(now))
            if self._job is not None:
                ready = max(ready, self._stream_allows_at(
                    self._job.sensor, self._job.plan[self._job.step], now))
            times.append(ready)
        return min(times)

    def _pick(self, now: float) -> Job | None:
        if self.stopping:
            return self._stops.popleft() if self._stops else None
        while self._commands:
            job = self._commands.popleft()
            if job.sensor.busy_until > now:
                self._finish(job, error=CommandError(ErrorKind.BUSY, f"{job.sensor.name} is "
                             f"busy for another {job.sensor.busy_until - now:.1f} s (save "
                             "or calibration)"))
                continue
            return job
        for s in self.sensors.values():
            if s.wants_stream(now):
                return Job(Kind.STREAM_START, s)
            if s.stop_stream and now >= s.stream_retry_at:
                s.stop_stream, s.stream_retry_at = False, now + STREAM_RETRY
                s.stats.stream_stops += 1
                self.stats.stream_stops += 1
                self._note(logging.WARNING, f"sensor {s.name}: streams though stream_hz is "
                           "0 (steady frames nobody asked for); stopping it")
                return Job(Kind.STREAM_STOP, s)
        for name, job in list(self._reads.items()):
            if job.sensor.busy_until > now:
                self._finish(job, error=CommandError(ErrorKind.BUSY, f"{name} is busy "
                                                     "(save or calibration)"))
            elif not job.sensor.streaming and not job.started:
                job.started = True  # stays listed until answered, for later askers
                return job
        due = [s for s in self.sensors.values() if s.due(now)]
        if due:
            return Job(Kind.POLL, min(due, key=lambda s: (s.next_due, s.last_served)))
        return None

    def _begin(self, job: Job, now: float) -> bool:
        """Make the job's exchanges; False (and finished) when it cannot have any."""
        s, series = job.sensor, job.sensor.config.series
        job.started = True
        try:
            match job.kind:
                case Kind.POLL | Kind.READ:
                    job.plan = [s.poll(self.adapter)]
                case Kind.STREAM_START:
                    job.plan = self.adapter.stream_start(series, s.address, s.config.stream_hz)
                case Kind.STREAM_STOP:
                    job.plan = self.adapter.stream_stop(series, s.address)
                case Kind.COMMAND:
                    assert job.command is not None
                    job.plan = self.adapter.command(series, s.address, job.command.name,
                                                    job.command.args)
        except UsageError as exc:  # Unsupported, or a value the protocol cannot carry
            self._job = None
            if job.kind is Kind.STREAM_START:
                self._note(logging.ERROR, f"sensor {s.name}: cannot stream at "
                           f"{s.config.stream_hz} Hz: {exc}")
                s.stream_retry_at = float("inf")
            kind = ErrorKind.UNSUPPORTED if isinstance(exc, Unsupported) else \
                ErrorKind.BAD_ARGUMENTS
            self._finish(job, error=CommandError(kind, str(exc)))
            return False
        return True

    # ------------------------------------------------------------ the line's timing

    def _line_free_at(self, now: float) -> float:
        """When the line is quiet enough for a request (in flight exchanges aside).

        After a whole answer it is known to be quiet and only the protocol's gap
        applies.  After noise or half a frame it must have been quiet 3.5 characters
        and ``MIN_QUIET``; a half frame that stopped coming is dropped then."""
        c = char_time(self.baud)
        gap = self.adapter.gap_before_request(self.baud)
        quiet = max(gap, 3.5 * c, MIN_QUIET)
        if self._framer.pending:
            if now < self._last_rx + quiet:
                return self._last_rx + quiet
            self._flush(now)
        settle = quiet if self._dirty else gap
        return max(self._last_rx + settle, self._last_tx_end + gap)

    def _stream_allows_at(self, s: SensorState, exchange: Exchange, now: float) -> float:
        """When ``exchange`` (to ``s``) may go next to the line's streaming sensor.

        It goes at once when it fits before the stream's next frame, with the sensor's
        answer latency as learned and a margin; otherwise in the pause after that frame.
        An exchange that never fits a pause goes right after a frame (best effort: its
        answer may meet the next one).  Frames that stop coming hold nothing up."""
        streamer = next((t for t in self.sensors.values() if t.streaming), None)
        if streamer is None:
            return now
        c = char_time(self.baud)
        period = 1 / streamer.config.stream_hz
        if not streamer.stream_frames and now < streamer.last_stream + 2 * period:
            return streamer.last_stream + 2 * period  # just set up: its first frame sets the phase
        frame = streamer.poll(self.adapter).answer_bytes * c
        gap = self.adapter.gap_before_request(self.baud)
        needs = (len(exchange.request) + exchange.answer_bytes) * c + 2 * gap + \
            s.timer.expected()
        return stream_wait(now, needs, streamer.last_stream, period, frame)

    def _send(self, job: Job, exchange: Exchange, now: float) -> Request:
        s, c = job.sensor, char_time(self.baud)
        gap = self.adapter.gap_before_request(self.baud)
        request_time = len(exchange.request) * c
        wire = request_time + exchange.answer_bytes * c + (gap if exchange.answer_bytes else 0)
        rto, hold = (s.timer.rto, s.timer.hold) if exchange.answer_bytes else (0.0, 0.0)
        if s.online is False:
            rto = hold  # probing an offline sensor: no back-off, it must cost the others little
        deadline = now + wire + rto
        self._attempt = Attempt(job, exchange, now, wire, deadline, deadline + hold,
                                now - gap, self.adapter.garbage_seen(self._framer))
        self._last_tx_end = now + request_time
        job.tries += 1
        return Request(exchange.request, exchange.answer_bytes)

    # ------------------------------------------------------------ what comes in

    def receive(self, data: bytes, at: float) -> None:
        """Bytes from the line; ``at``: when the last of them came in."""
        self._last_rx = at
        garbage = self.adapter.garbage_seen(self._framer)
        for frame in self._framer.feed(data):
            self._frame(frame, at)
        # Bytes that did not end in a whole frame (noise, half a frame) may be followed
        # by more: the next request then waits for the line to be quiet.
        self._dirty = bool(self._framer.pending) or \
            self.adapter.garbage_seen(self._framer) > garbage

    def _frame(self, frame: Any, at: float) -> None:
        a = self._attempt
        if a is not None:
            answer = a.exchange.match(frame)
            if answer is not None:
                self._answered(a, answer, at)
                return
        for s in self.sensors.values():
            answer = self.adapter.unsolicited(frame, s.config.series, s.address)
            if answer is not None:
                self._unsolicited(s, answer, at)
                return
        self.stats.errors["unexpected_frame"] += 1
        # Some other frame from one of ours (a sensor left streaming its angles alone,
        # say): evidence of a stream, though not a reading of what it is polled for.
        sender = getattr(frame, "unit", getattr(frame, "address", None))
        for s in self.sensors.values():
            if s.address == sender and not s.streaming:
                self._stray(s, None, at)

    def _unsolicited(self, s: SensorState, answer: Answer, at: float) -> None:
        if answer.values.get("done"):
            s.busy_until = 0.0
            self._note(logging.INFO, f"sensor {s.name}: gyro calibration done")
            self._events.append(StateChange(s.name, busy=False))
            return
        if s.streaming:
            s.last_stream = at
            s.stream_frames += 1
            self._reading(s, answer, at)
            return
        self.stats.errors["unexpected_frame"] += 1
        self._stray(s, answer, at)

    def _stray(self, s: SensorState, answer: Answer | None, at: float) -> None:
        """A frame from ``s`` that answers nothing of ours: a late answer, or a stream."""
        s.stats.errors["unexpected_frame"] += 1
        outstanding = self._attempt is not None and self._attempt.job.sensor is s
        if outstanding or s.explained(at):
            return  # an answer to a request of ours, too late to use: not a reading
        if s.unasked_frame(at):
            if s.config.stream_hz and answer is not None:
                s.streaming, s.last_stream = True, at
                self._events.append(StateChange(s.name, streaming=True))
                self._note(logging.INFO, f"sensor {s.name}: its stream is back")
            elif not s.config.stream_hz:
                s.stop_stream = True
        if answer is not None:
            self._reading(s, answer, at)

    def _reading(self, s: SensorState, answer: Answer, at: float) -> None:
        """A reading of ``s``: to the cache, and to whoever asked for a fresh one."""
        self._events.append(Publish(s.name, answer, at))
        self._succeeded(s)
        job = self._reads.get(s.name)
        if job is not None:  # a fresh reading, from a poll or a stream frame
            self._finish(job)

    # ------------------------------------------------------------ timers

    def handle_timer(self, now: float, pending: int = 0) -> None:
        """Deadlines, streams that stopped, busy periods that ended.  ``pending``: bytes
        the port holds that ``receive`` has not had yet (a busy machine's timer fires
        late; the answer may be in already)."""
        a = self._attempt
        if a is not None:
            self._attempt_timer(a, now, pending)
        for s in self.sensors.values():
            if s.streaming and now - s.last_stream > s.stream_timeout:
                s.streaming = False
                s.stream_retry_at = now + STREAM_RETRY
                s.next_due = now
                self._events.append(StateChange(s.name, streaming=False))
                self._note(logging.WARNING, f"sensor {s.name}: its stream stopped; polling it")
            if s.busy_until and now >= s.busy_until:
                s.busy_until = 0.0
                self._events.append(StateChange(s.name, busy=False))

    def _attempt_timer(self, a: Attempt, now: float, pending: int) -> None:
        if not a.exchange.answer_bytes:
            if now >= a.deadline:  # a request nobody answers: done once it is out
                self._answered(a, Answer({}), now)
            return
        arriving = pending > 0 or bool(self._framer.pending)
        if not a.overdue:
            if now < a.deadline:
                return
            if arriving:  # the answer is coming in: wait for it, not for the timeout
                a.deadline = now + max(pending, 1) * char_time(self.baud) + MIN_QUIET
                a.give_up = max(a.give_up, a.deadline)
                return
            a.overdue = True
        if now < a.give_up:
            return
        if arriving and now < a.give_up + ARRIVING_GRACE:
            a.give_up = now + max(pending, 1) * char_time(self.baud) + MIN_QUIET
            return
        self._timed_out(a, now)

    def _timed_out(self, a: Attempt, now: float) -> None:
        s, job = a.job.sensor, a.job
        kind = "bad_frame" if self.adapter.garbage_seen(self._framer) > a.garbage else "timeout"
        self._count_error(s, kind)
        self._account(a, now)
        self._attempt = None
        s.unanswered.append(a.sent)
        s.timer.timed_out()
        self._flush(now)
        if job.tries <= self.config.retries:
            return  # the same exchange goes again
        self._fail_job(job, now, kind, f"{s.name} did not answer ({kind})")

    # ------------------------------------------------------------ outcomes

    def _answered(self, a: Attempt, answer: Answer, at: float) -> None:
        s, job = a.job.sensor, a.job
        self._attempt = None
        if a.exchange.answer_bytes:
            s.timer.sample(at - a.sent - a.wire)
            if a.overdue:
                s.stats.late_answers += 1
                self.stats.late_answers += 1
        self._account(a, at)
        self.stats.transactions += 1
        s.stats.transactions += 1
        self.stats.rate.add(at)
        gap = self.adapter.gap_before_request(self.baud)
        self.stats.wire_time += a.wire + gap
        job.tries = 0
        if job.kind in (Kind.POLL, Kind.READ):
            self._polled(job, answer, at)
            return
        if a.exchange.answer_bytes:  # a write nobody answers proves nothing about s
            self._succeeded(s)
        if not answer.ok:
            self._refused(job, answer, at)
            return
        self._apply(s, a.exchange.effect, at)
        job.values.update(answer.values)
        job.step += 1
        if job.step == len(job.plan):
            self._done(job, at)

    def _polled(self, job: Job, answer: Answer, at: float) -> None:
        s = job.sensor
        self._job = None
        if not answer.ok:  # a Modbus exception, or a frame that did not decode
            self._count_error(s, "refused")
            self._fail_job(job, at, "refused", f"{s.name} did not answer (refused)")
            return
        s.last_served = at
        self._reading(s, answer, at)
        s.schedule_next_poll(at)

    def _refused(self, job: Job, answer: Answer, at: float) -> None:
        s = job.sensor
        self._job = None
        if job.kind is Kind.STREAM_START:
            self._note(logging.WARNING, f"sensor {s.name}: refused auto-output: {answer.detail}")
            s.stream_retry_at = at + STREAM_RETRY
            return
        if job.kind is Kind.COMMAND:
            assert job.command is not None
            self._finish(job, CommandResult(s.name, job.command.name, False, dict(answer.values),
                                            f"{s.name}: {answer.detail}", ErrorKind.FAILURE))
            return
        self._finish(job, answer.values.get("pdu"))

    def _done(self, job: Job, at: float) -> None:
        s = job.sensor
        self._job = None
        match job.kind:
            case Kind.STREAM_START:
                s.streaming, s.last_stream, s.stream_frames = True, at, 0
                self._events.append(StateChange(s.name, streaming=True))
                self._note(logging.INFO, f"sensor {s.name}: streaming at "
                           f"{s.config.stream_hz:g} Hz")
            case Kind.COMMAND:
                assert job.command is not None
                if job.command.name == "read_settings":
                    job.values["address"] = s.address
                self._note(logging.INFO, f"sensor {s.name}: {job.command.name} "
                           f"{dict(job.command.args) or ''} done")
                self._finish(job, CommandResult(s.name, job.command.name, True, job.values))
            case Kind.PASSTHROUGH:
                self._finish(job, job.values.get("pdu"))
            case _:
                pass

    def _fail_job(self, job: Job, now: float, kind: str, message: str) -> None:
        s = job.sensor
        if job is self._job:
            self._job = None
        was = s.online
        if kind != "port_lost" and s.failed():
            self._note(logging.WARNING, f"sensor {s.name}: offline "
                       f"({'never answered' if was is None else kind})")
            self._events.append(StateChange(s.name, online=False))
        error_kind = {"port_lost": ErrorKind.OFFLINE, "refused": ErrorKind.FAILURE}.get(
            kind, ErrorKind.TIMEOUT)
        if job.kind is Kind.STREAM_START:
            s.stream_retry_at = now + STREAM_RETRY
        if job.kind in (Kind.POLL, Kind.READ):
            s.last_served = now
            s.schedule_next_poll(now)
        self._finish(job, error=CommandError(error_kind, message))

    def _finish(self, job: Job, outcome: CommandResult | bytes | None = None,
                error: CommandError | None = None) -> None:
        if self._reads.get(job.sensor.name) is job:
            del self._reads[job.sensor.name]
        if job.kind in (Kind.POLL, Kind.STREAM_START, Kind.STREAM_STOP):
            return  # nobody waits for these
        if error is not None and job.command is not None:
            outcome = CommandResult.failed(job.sensor.name, job.command.name, error)
            error = None
        self._events.append(Finished(job, outcome, error))

    def _apply(self, s: SensorState, effect: Effect, at: float) -> None:
        if effect.new_baud is not None and effect.new_baud != self.baud:
            self._note(logging.WARNING, f"bus {self.config.name}: following {s.name} from "
                       f"{self.baud} to {effect.new_baud} baud")
            self.baud = effect.new_baud  # the driver switches the port before writing
        if effect.new_address is not None and effect.new_address != s.address:
            self._note(logging.WARNING, f"sensor {s.name}: now at address "
                       f"{effect.new_address} (the config says {s.config.address})")
            s.address = effect.new_address
        if effect.busy_for or effect.busy_until_done:
            s.busy_until = at + (GYRO_CAL_SECONDS if effect.busy_until_done else effect.busy_for)
            self._events.append(StateChange(s.name, busy=True))

    # ------------------------------------------------------------ bookkeeping

    def _account(self, a: Attempt, end: float) -> None:
        """The attempt's time on the line.  The silent gap before the request counts,
        but not twice: it starts at the exchange before, counted up to its end."""
        took = max(0.0, end - max(a.started, self._busy_end))
        self._busy_end = max(self._busy_end, end)
        self.stats.busy_time += took
        a.job.sensor.stats.busy_time += took

    def _count_error(self, s: SensorState, kind: str) -> None:
        self.stats.errors[kind] += 1
        s.stats.errors[kind] += 1
        self._events.append(ErrorCounted(s.name))

    def _flush(self, now: float) -> None:
        """A half frame that stopped coming will never complete: whatever it held."""
        while self._framer.pending:
            for frame in self._framer.expire():
                self._frame(frame, now)
        self._dirty = False

    def _succeeded(self, s: SensorState) -> None:
        change = s.succeeded()
        if change is not None:
            self._note(logging.INFO, f"sensor {s.name}: {change}")
            self._events.append(StateChange(s.name, online=True))

    def _note(self, level: int, text: str) -> None:
        self._events.append(Note(level, text))
