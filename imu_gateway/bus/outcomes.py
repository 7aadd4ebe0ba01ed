"""What the answers, silences and stray frames on a line mean, sans-IO: the outcome
of each attempt and job (results, readings, effects on the bus), online and offline,
late answers, and the evidence that a sensor streams unasked.  Part of ``Schedule``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

from ..commands import CATALOGUE, CommandResult
from ..config import BusConfig
from ..errors import ErrorKind, RequestFailed
from ..model import WireProtocol
from ..protocol.exchanges import (
    GYRO_CAL_SECONDS,
    Answer,
    Effect,
    Frame,
    ProtocolAdapter,
    sender,
)
from ..stats import Counters
from .diagnosis import Diagnosis
from .events import (
    Attempt,
    ErrorCounted,
    Event,
    Job,
    Kind,
    Note,
    Publish,
    StateChange,
    Trace,
)
from .jobs import JobQueue
from .line import Line
from .sensor_state import SETTINGS_RETRY, STREAM_RETRY, SensorState

#: Modbus function codes that change the device (a pass-through of one is a write).
MODBUS_WRITES = frozenset({0x05, 0x06, 0x0F, 0x10, 0x16, 0x17})


def changes_sensor(job: Job) -> bool:
    """Whether ``job`` may have changed the sensor, and sending it again could change it
    again: a command whose catalogue row is not ``idempotent``, or a Modbus
    pass-through write.  Its lost answer is not retried (docs/bus-master.md)."""
    if job.kind is Kind.COMMAND and job.command is not None:
        return not CATALOGUE[job.command.name].idempotent
    if job.kind is Kind.PASSTHROUGH:
        request = job.plan[0].request
        return len(request) > 1 and request[1] in MODBUS_WRITES
    return False


class Outcomes:
    def __init__(self, config: BusConfig, adapter: ProtocolAdapter,
                 sensors: dict[str, SensorState], jobs: JobQueue, line: Line,
                 stats: Counters, emit: Callable[[Event], None],
                 diagnosis: Diagnosis) -> None:
        self.config = config
        self.adapter = adapter
        self.sensors = sensors
        self.jobs = jobs
        self.line = line
        self.stats = stats
        self.emit = emit
        self.diagnosis = diagnosis
        self.tracing = config.trace  # emit a Trace per exchange (the driver may turn it on)
        self.traced = 0  # Trace events made: none while nobody traces (a test holds it)

    def frame(self, frame: Frame, at: float) -> None:
        """A whole frame came in at ``at``: the answer in flight, a stream frame, a
        late answer, or evidence of a stream nobody asked for."""
        self.diagnosis.frame(frame)
        a = self.line.attempt
        if a is not None:
            answer = a.exchange.match(frame)
            # Bytes that matched the request are its answer, however early: many
            # sensors answer well inside RTU's 3.5-character gap, and on a busy machine
            # a read's times are late and bunched, so they cannot tell early from late.
            # Only an answer in before the request was written is surely an older one's.
            if answer is not None and at >= a.sent:
                if at < a.sent + a.wire - self.line.char:  # sooner than the gap allows
                    s = a.job.sensor
                    s.stats.early_answers += 1
                    self.stats.early_answers += 1
                self.answered(a, answer, at)
                return
        for s in self.sensors.values():
            answer = self.adapter.unsolicited(frame, s.config.series, s.address)
            if answer is not None:
                self._unsolicited(s, answer, at)
                return
        self.stats.errors["unexpected_frame"] += 1
        # Some other frame from one of ours (a sensor left streaming its angles alone,
        # say): evidence of a stream, though not a reading of what it is polled for.
        address = sender(frame)
        for s in self.sensors.values():
            if s.address != address or s.streaming:
                continue
            misfit = self.diagnosis.misfit(frame, s.config.series)
            if misfit is None:
                self._stray(s, None, at)
            elif self.diagnosis.first(s.name, misfit):  # an answer, of the wrong shape: no stream
                self._note(logging.WARNING, f"sensor {s.name}: {misfit}")

    def _unsolicited(self, s: SensorState, answer: Answer, at: float) -> None:
        if answer.values.get("done"):
            s.busy_until = 0.0
            self._note(logging.INFO, f"sensor {s.name}: gyro calibration done")
            self.emit(StateChange(s.name, busy=False))
            return
        if s.streaming:
            s.stream_frame(at)
            self._reading(s, answer, at)
            return
        self.stats.errors["unexpected_frame"] += 1
        self._stray(s, answer, at)

    def _stray(self, s: SensorState, answer: Answer | None, at: float) -> None:
        """A frame from ``s`` that answers nothing of ours: a late answer, or a stream."""
        s.stats.errors["unexpected_frame"] += 1
        a = self.line.attempt
        outstanding = a is not None and a.job.sensor is s
        if outstanding or s.explained(at):
            return  # an answer to a request of ours, too late to use: not a reading
        if s.unasked_frame(at):
            if s.config.stream_hz and answer is not None:
                s.stream_started(at)
                s.stream_frame(at)  # (this frame is one of it)
                self.emit(StateChange(s.name, streaming=True))
                self._note(logging.INFO, f"sensor {s.name}: its stream is back")
            elif not s.config.stream_hz:
                s.stop_stream = True
        if answer is not None:
            self._reading(s, answer, at)

    def _reading(self, s: SensorState, answer: Answer, at: float) -> None:
        """A reading of ``s``: to the cache, and to whoever asked for a fresh one."""
        self.emit(Publish(s.name, answer, at))
        self._succeeded(s)
        job = self.jobs.reads.get(s.name)
        if job is not None:  # a fresh reading, from a poll or a stream frame
            self.jobs.finish(job)

    def timed_out(self, a: Attempt, now: float) -> None:
        """The attempt got no answer, not even late: retry it, or fail its job."""
        s, job = a.job.sensor, a.job
        kind = self.line.failure_kind(a)
        if self.tracing:
            self._trace(a, now, f"{kind} (try {job.tries} of {self.config.retries + 1})")
        self._count_error(s, kind)
        self.line.close(a, now, answered=False)
        if kind == "timeout":  # silence: its answer may still come (a garbled one came)
            s.unanswered.append(a.sent)
            s.timer.timed_out()
        self.line.flush(now)
        if changes_sensor(job):  # it may have been carried out: never sent twice
            what = job.command.name if job.command is not None else "the write"
            self.fail_job(job, now, "unconfirmed", f"{s.name}: {what} was sent but not "
                          f"confirmed ({kind}): read the setting back before sending it again")
            return
        if job.tries <= self.config.retries:
            return  # the same exchange goes again
        self.fail_job(job, now, kind, f"{s.name} did not answer ({kind})")

    def answered(self, a: Attempt, answer: Answer, at: float) -> None:
        """The attempt's answer (a late one too): on to the job's next step."""
        s, job = a.job.sensor, a.job
        if a.exchange.answer_bytes and (job.tries > 1 or s.suspect(a.sent)):
            # A retry answered, or any request to a sensor that lately left one
            # unanswered: the answer may be that request's, late, with this one's own
            # still to come.  Nothing goes out while that one may still come (and, as
            # Karn's rule says, the answer times nothing: whose is it?).
            self.line.hold_until = max(self.line.hold_until, a.give_up)
        elif a.exchange.answer_bytes and not a.untimed:  # (untimed: a slow write)
            if a.looked:  # found whole when looked for: it came in before, when?
                s.timer.answered()
            else:
                s.timer.sample(at - a.sent - a.wire)
        if a.exchange.answer_bytes and a.overdue:
            s.stats.late_answers += 1
            self.stats.late_answers += 1
        if self.tracing:
            self._trace(a, at, "ok" if answer.ok and not a.overdue else
                        "late" if answer.ok else f"refused ({answer.detail})")
        self.line.close(a, at, answered=True)
        job.tries = 0
        if job.kind in (Kind.POLL, Kind.READ):
            self._polled(job, answer, at)
            return
        if a.exchange.answer_bytes:  # a write nobody answers proves nothing about s
            self._succeeded(s)
        if not answer.ok:
            self._refused(job, answer, at)
            return
        self._apply(s, answer.effect if answer.effect is not None else a.exchange.effect, at)
        job.values.update(answer.values)
        job.step += 1
        if job.step == len(job.plan):
            self._done(job, at)

    def _polled(self, job: Job, answer: Answer, at: float) -> None:
        s = job.sensor
        self.jobs.current = None
        if not answer.ok:  # a Modbus exception, or a frame that did not decode
            self._count_error(s, "refused")
            self.fail_job(job, at, "refused", f"{s.name} did not answer (refused)")
            return
        s.last_served = at
        self._reading(s, answer, at)
        s.schedule_next_poll(at)

    def _refused(self, job: Job, answer: Answer, at: float) -> None:
        s = job.sensor
        self.jobs.current = None
        if job.kind is Kind.STREAM_START:
            self._note(logging.WARNING, f"sensor {s.name}: refused auto-output: {answer.detail}")
            s.stream_retry_at = at + STREAM_RETRY
            return
        if job.kind is Kind.SETTINGS:
            s.settings_at = math.inf  # it refuses: asking again would not help
        if job.kind in (Kind.COMMAND, Kind.SETTINGS):
            assert job.command is not None
            self.jobs.finish(job, CommandResult(
                s.name, job.command.name, False, dict(answer.values),
                f"{s.name}: {answer.detail}", ErrorKind.FAILURE))
            return
        self.jobs.finish(job, answer.values.get("pdu"))

    def _done(self, job: Job, at: float) -> None:
        s = job.sensor
        self.jobs.current = None
        match job.kind:
            case Kind.STREAM_START:
                s.stream_started(at)
                self.emit(StateChange(s.name, streaming=True))
                self._note(logging.INFO, f"sensor {s.name}: streaming at "
                           f"{s.config.stream_hz:g} Hz")
            case Kind.COMMAND | Kind.SETTINGS:
                assert job.command is not None
                if job.command.name == "read_settings":
                    job.values["address"] = s.address
                if job.kind is Kind.SETTINGS:
                    s.settings_at = math.inf
                    self._note(logging.INFO, f"sensor {s.name}: its settings read again "
                               f"(a power cut may have reset them): {job.values}")
                else:
                    self._note(logging.INFO, f"sensor {s.name}: {job.command.name} "
                               f"{dict(job.command.args) or ''} done")
                self.jobs.finish(job, CommandResult(s.name, job.command.name, True, job.values))
            case Kind.PASSTHROUGH:
                self.jobs.finish(job, job.values.get("pdu"))
            case _:
                pass

    def fail_job(self, job: Job, now: float, kind: str, message: str) -> None:
        s = job.sensor
        if job is self.jobs.current:
            self.jobs.current = None
        was = s.online
        if kind not in ("port_lost", "internal") and s.failed():
            self._note(logging.WARNING, self._offline(s, kind, never=was is None))
            self.emit(StateChange(s.name, online=False))
        error_kind = {"port_lost": ErrorKind.OFFLINE, "internal": ErrorKind.OFFLINE,
                      "refused": ErrorKind.FAILURE,
                      "unconfirmed": ErrorKind.UNCONFIRMED}.get(kind, ErrorKind.TIMEOUT)
        if job.kind is Kind.STREAM_START:
            s.stream_retry_at = now + STREAM_RETRY
        if job.kind is Kind.SETTINGS:
            s.settings_at = now + SETTINGS_RETRY
        if job.kind in (Kind.POLL, Kind.READ):
            s.last_served = now
            s.schedule_next_poll(now)
        self.jobs.finish(job, error=RequestFailed(error_kind, message))

    def _trace(self, a: Attempt, at: float, outcome: str) -> None:
        """(Called only while tracing: the outcome's words are not built otherwise.)"""
        self.traced += 1
        self.emit(Trace(a.job.sensor.name, a.exchange.request, bytes(self.line.heard),
                        at - a.sent, outcome if a.exchange.answer_bytes else "sent",
                        a.placed, at))

    def _offline(self, s: SensorState, kind: str, never: bool) -> str:
        """The log line for a sensor going offline: where it was asked, and for one
        that never answered, what the line suggests is wrong."""
        baud = self.line.baud
        where = (f"native address {s.address}" if self.config.protocol is WireProtocol.NATIVE
                 else f"Modbus unit {s.address}") + f" at {baud} baud"
        if never:
            cause = self.diagnosis.cause(s.name, s.address, baud,
                                         {t.address for t in self.sensors.values()})
            return f"sensor {s.name}: offline (never answered, {where}): {cause}"
        return f"sensor {s.name}: offline ({kind}, {where})"

    def _apply(self, s: SensorState, effect: Effect, at: float) -> None:
        if effect.new_baud is not None and effect.new_baud != self.line.baud:
            self._note(logging.WARNING, f"bus {self.config.name}: following {s.name} from "
                       f"{self.line.baud} to {effect.new_baud} baud")
            self.line.baud = effect.new_baud  # the driver switches the port before writing
        if effect.new_address is not None and effect.new_address != s.address:
            self._note(logging.WARNING, f"sensor {s.name}: now at address "
                       f"{effect.new_address} (the config says {s.config.address})")
            s.address = effect.new_address
        if effect.busy_for or effect.busy_until_done:
            s.busy_until = at + (GYRO_CAL_SECONDS if effect.busy_until_done else effect.busy_for)
            s.read_while_busy = effect.read_while_busy
            self.emit(StateChange(s.name, busy=True))

    # ------------------------------------------------------------ bookkeeping

    def _count_error(self, s: SensorState, kind: str) -> None:
        self.stats.errors[kind] += 1
        s.stats.errors[kind] += 1
        self.emit(ErrorCounted(s.name))

    def _succeeded(self, s: SensorState) -> None:
        change = s.succeeded()
        if change is not None:
            self._note(logging.INFO, f"sensor {s.name}: {change}")
            self.emit(StateChange(s.name, online=True))

    def _note(self, level: int, text: str) -> None:
        self.emit(Note(level, text))
