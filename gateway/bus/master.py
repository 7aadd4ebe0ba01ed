"""The bus master: the one owner of a serial line.

Everything that reaches a sensor goes through here, one exchange on the wire at a
time.  What goes next is decided by priority:

1. commands (from any front end), first come first served;
2. setting up a sensor's auto-output stream (``stream_hz``);
3. on-demand reads ("a reading no older than N ms"), one per sensor however many
   clients ask;
4. background polls: each sensor at its ``poll_hz``; ``0`` means as often as the
   line allows.  The due sensor that waited longest goes first, so when the sensors
   ask for more than the wire can carry they all slow down evenly, and the missed
   polls are counted.

An exchange ends the moment its answer's last byte is in (the framer knows the
length), or after the wire time plus ``timeout_ms``.  A sensor that keeps failing
is polled with growing back-off so a dead address costs the others little; it is
marked offline after ``OFFLINE_AFTER`` failures and online again at its first answer.
A lost port marks every sensor offline and is reopened with back-off, for ever.

The protocol specifics (frames, answer matching, the quirks of baud, address and
save) come from ``protocol.exchanges``; this module only carries them out.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import time
import typing
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any

from ..cache import SensorUnavailable
from ..commands import Command, CommandError, CommandResult, ErrorKind
from ..config import BusConfig, SensorConfig
from ..model import Reading
from ..normalise import to_reading
from ..protocol.errors import UsageError
from ..protocol.exchanges import (
    GYRO_CAL_SECONDS,
    Answer,
    Effect,
    Exchange,
    ModbusAdapter,
    Unsupported,
    adapter_for,
    char_time,
)
from .link import LinkError, SerialLink

log = logging.getLogger("gateway.bus")

OFFLINE_AFTER = 3  # consecutive failed exchanges before a sensor is called offline
BACKOFF_MIN, BACKOFF_MAX = 0.25, 10.0  # seconds between tries of a failing sensor
REOPEN_MIN, REOPEN_MAX = 0.5, 5.0  # seconds between tries to reopen a lost port
STREAM_RETRY = 5.0  # seconds before setting up a stream that stopped again
RATE_WINDOW = 5.0  # seconds over which achieved rates are measured
MAX_QUEUED_PER_SENSOR = 16  # commands waiting for one sensor before more are refused (busy)
LATE_ANSWER_GRACE = 0.1  # after a timeout, keep quiet this long (at most) for a late answer
MIN_QUIET = 0.001  # the line must have been quiet this long before a request goes out
SLOW_STREAM = 0.2  # stream periods from this long on are not waited for by every exchange
# A sensor is taken to stream unasked only after this many unasked-for frames within
# STRAY_WINDOW seconds: one such frame is usually a late answer (a busy machine).
STRAY_EVIDENCE, STRAY_WINDOW = 3, 2.0
STREAM_MARGIN = 0.02  # room left before a slow stream's next frame


def _time_out(future: asyncio.Future[Any]) -> None:
    if not future.done():
        future.set_exception(TimeoutError())


class Priority(enum.IntEnum):
    COMMAND = 0
    STREAM_SETUP = 1
    ON_DEMAND = 2
    POLL = 3


class _Failed(Exception):
    def __init__(self, kind: str) -> None:
        super().__init__(kind)
        self.kind = kind


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
class SensorStats:
    transactions: int = 0
    readings: int = 0
    missed_polls: int = 0
    busy_time: float = 0.0  # bus time this sensor's exchanges took, failed ones too
    errors: Counter[str] = field(default_factory=Counter)
    rate: RateMeter = field(default_factory=RateMeter)


@dataclass(slots=True)
class BusStats:
    started: float = 0.0
    transactions: int = 0
    errors: Counter[str] = field(default_factory=Counter)
    busy_time: float = 0.0  # the line was ours: request, answer delay, answer, gaps
    wire_time: float = 0.0  # the bytes of the exchanges done, at the wire's rate
    rate: RateMeter = field(default_factory=RateMeter)

    def utilisation(self, now: float) -> float:
        elapsed = now - self.started
        return self.busy_time / elapsed if elapsed > 0 else 0.0

    def wire_utilisation(self, now: float) -> float:
        elapsed = now - self.started
        return self.wire_time / elapsed if elapsed > 0 else 0.0


@dataclass(eq=False, slots=True)
class Sensor:
    """A sensor's run-time state on its bus."""

    config: SensorConfig
    address: int
    next_due: float = 0.0
    last_served: float = 0.0
    failures: int = 0
    online: bool | None = None  # None: not heard from yet
    busy_until: float = 0.0
    streaming: bool = False
    stop_stray_stream: bool = False  # it streams though nobody asked: tell it to stop
    stray_frames: list[float] = field(default_factory=list)  # when unasked-for frames came
    last_stream: float = 0.0
    stream_retry_at: float = 0.0
    stats: SensorStats = field(default_factory=SensorStats)

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def period(self) -> float:
        return 1 / self.config.poll_hz if self.config.poll_hz > 0 else 0.0

    @property
    def stream_timeout(self) -> float:
        return max(5 / self.config.stream_hz, 0.5) if self.config.stream_hz else 0.0

    def wants_stream(self, now: float) -> bool:
        return bool(self.config.stream_hz) and not self.streaming \
            and now >= self.stream_retry_at and now >= self.busy_until


@dataclass(eq=False, slots=True)
class Job:
    priority: Priority
    sensor: Sensor
    command: Command | None = None
    future: asyncio.Future[Any] | None = None
    plan: list[Exchange] | None = None  # exchanges ready made (pass-through)
    started: bool = False  # an on-demand read in flight: later askers share it


#: the master's on-demand read of one sensor
ReadNow = typing.Callable[[str], typing.Coroutine[typing.Any, typing.Any, None]]


class CacheWrites(typing.Protocol):
    """What a bus master writes to the cache (``Cache`` itself, or a ``CacheWriter`` that
    hands the writes to another thread's loop)."""

    def publish(self, name: str, reading: Reading, at: float | None = None) -> object: ...

    def set_state(self, name: str, *, online: bool | None = None, busy: bool | None = None,
                  streaming: bool | None = None) -> None: ...

    def count_error(self, name: str) -> None: ...

    def set_requester(self, name: str, requester: ReadNow) -> None: ...


class BusMaster:
    def __init__(self, config: BusConfig, cache: CacheWrites,
                 link: SerialLink | None = None) -> None:
        self.config = config
        self.name = config.name
        self.baud = config.baudrate
        self.adapter = adapter_for(config.protocol)
        self.timeout = config.effective_timeout_ms() / 1000
        self.link = link or SerialLink(config.port, config.baudrate, rs485=config.rs485)
        self.cache = cache
        self.sensors = {s.name: Sensor(s, s.address) for s in config.sensors}
        for name in self.sensors:
            cache.set_requester(name, self.read_now)
        self.stats = BusStats()
        self.port_open = False
        self._framer = self.adapter.new_framer()
        self._commands: deque[Job] = deque()
        self._on_demand: dict[str, Job] = {}
        self._waiting: tuple[Exchange, asyncio.Future[Answer]] | None = None
        self._wake = asyncio.Event()
        self._stream_frame = asyncio.Event()
        self._stopping = False
        self._last_rx = 0.0
        self._last_tx_end = 0.0
        self._busy_end = 0.0  # when the last exchange counted in busy_time ended
        self._quiet_until = 0.0
        self._dirty = False
        self._polls: dict[str, tuple[int, Exchange]] = {}
        self._reopen_delay = REOPEN_MIN
        self._port_problem_logged = False
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------ public interface

    def _refusal(self, s: Sensor, queued: bool = True) -> CommandError | None:
        """Why a request for ``s`` cannot be taken now (it is answered at once), or None.

        A sensor in back-off is not asked on demand: that would undo the back-off and
        hand the line to a dead address (it is still retried in the background)."""
        if self._stopping:
            return CommandError(ErrorKind.OFFLINE, "the gateway is stopping")
        if not self.port_open:
            return CommandError(ErrorKind.OFFLINE,
                                f"the port of bus {self.name} ({self.config.port}) is not open")
        if s.online is False:
            return CommandError(ErrorKind.OFFLINE, f"{s.name} is offline (it is retried in "
                                f"the background; {s.failures} failed exchanges so far)")
        if queued and sum(j.sensor is s for j in self._commands) >= MAX_QUEUED_PER_SENSOR:
            return CommandError(ErrorKind.BUSY, f"{MAX_QUEUED_PER_SENSOR} requests for {s.name} "
                                "are already waiting")
        return None

    async def submit(self, sensor: str, command: Command) -> CommandResult:
        """Carry out a validated command; returns after the sensor's answer."""
        s = self.sensors[sensor]
        if (refusal := self._refusal(s)) is not None:
            return CommandResult.failed(sensor, command.name, refusal)
        future: asyncio.Future[CommandResult] = asyncio.get_running_loop().create_future()
        self._commands.append(Job(Priority.COMMAND, s, command, future))
        self._wake.set()
        return await future

    async def passthrough(self, sensor: str, pdu: bytes) -> bytes:
        """A Modbus request PDU to the sensor unchanged, queued like a command; returns
        the sensor's answer PDU (its exceptions included).  Raises ``SensorUnavailable``
        when it does not answer."""
        s = self.sensors[sensor]
        if (refusal := self._refusal(s)) is not None:
            raise SensorUnavailable(refusal.kind, str(refusal))
        if not isinstance(self.adapter, ModbusAdapter):
            raise SensorUnavailable(ErrorKind.UNSUPPORTED, f"{sensor} does not speak Modbus")
        future: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        plan = [self.adapter.raw(s.address, pdu)]
        self._commands.append(Job(Priority.COMMAND, s, None, future, plan))
        self._wake.set()
        return await future

    async def read_now(self, sensor: str) -> None:
        """Read the sensor now (behind commands).  Concurrent calls share one exchange;
        a streaming sensor's next frame serves them.  Raises ``SensorUnavailable``."""
        s = self.sensors[sensor]
        if (refusal := self._refusal(s, queued=False)) is not None:
            raise SensorUnavailable(refusal.kind, str(refusal))
        job = self._on_demand.get(sensor)
        if job is None:
            job = Job(Priority.ON_DEMAND, s, None, asyncio.get_running_loop().create_future())
            self._on_demand[sensor] = job
            self._wake.set()
        assert job.future is not None
        await asyncio.shield(job.future)

    def stop(self) -> None:
        """Finish the exchange in flight, then stop."""
        self._stopping = True
        self._wake.set()

    def queue_depth(self) -> int:
        return len(self._commands) + len(self._on_demand)

    # ------------------------------------------------------------ the loop

    async def run(self) -> None:
        self._loop = loop = asyncio.get_running_loop()
        self.stats.started = self.stats.rate.started = loop.time()
        for s in self.sensors.values():
            s.stats.rate.started = self.stats.started
        try:
            while not self._stopping:
                if not self.port_open:
                    await self._open_port()
                    continue
                now = loop.time()
                self._housekeeping(now)
                job = self._next_job(now)
                if job is None:
                    await self._idle(self._next_wake(now) - now)
                    continue
                await self._execute(job)
        finally:
            await self._shutdown()

    async def _idle(self, timeout: float) -> None:
        self._wake.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._wake.wait(), max(0.0, timeout))

    def _now(self) -> float:
        # The event loop's clock is time.monotonic; before run() there is no loop yet.
        return self._loop.time() if self._loop is not None else time.monotonic()

    # ------------------------------------------------------------ the port

    async def _open_port(self) -> None:
        try:
            await self.link.open(self._on_bytes, self._on_lost)
            self.link.set_baudrate(self.baud)
        except LinkError as exc:
            self.link.close()
            if not self._port_problem_logged:
                log.warning("bus %s: %s; retrying", self.name, exc)
                self._port_problem_logged = True
            self._all_offline()
            self._fail_pending(ErrorKind.OFFLINE, f"the port of bus {self.name} is not open")
            await self._idle(self._reopen_delay)
            self._reopen_delay = min(self._reopen_delay * 2, REOPEN_MAX)
            return
        if self._port_problem_logged:
            log.warning("bus %s: port %s is back", self.name, self.config.port)
        else:
            log.info("bus %s: port %s open at %d baud", self.name, self.config.port, self.baud)
        self._port_problem_logged = False
        self._reopen_delay = REOPEN_MIN
        self._framer = self.adapter.new_framer()
        self.port_open = True
        now = self._now()
        for s in self.sensors.values():
            s.next_due, s.streaming, s.stream_retry_at = now, False, now

    def _on_lost(self, exc: Exception) -> None:
        """The port is gone (reported by the reader or by a failed write): once."""
        if not self.port_open:
            return
        self.link.close()
        self.port_open = False
        self.stats.errors["port_lost"] += 1
        log.warning("bus %s: port %s lost (%s); reopening", self.name, self.config.port, exc)
        self._port_problem_logged = True
        if self._waiting is not None and not self._waiting[1].done():
            self._waiting[1].set_exception(_Failed("port_lost"))
        self._all_offline()
        self._wake.set()

    def _all_offline(self) -> None:
        for s in self.sensors.values():
            if s.online is not False:
                s.online = False
                self.cache.set_state(s.name, online=False, streaming=False)
            s.streaming = False

    def _fail_pending(self, kind: ErrorKind, message: str) -> None:
        while self._commands:
            job = self._commands.popleft()
            self._fail(job, kind, message)
        for job in list(self._on_demand.values()):
            self._fail(job, kind, message)
        self._on_demand.clear()

    # ------------------------------------------------------------ receiving

    def _on_bytes(self, data: bytes) -> None:
        now = self._now()
        self._last_rx = now
        garbage = self.adapter.garbage_seen(self._framer)
        for frame in self._framer.feed(data):
            self._on_frame(frame, now)
        # Bytes that did not end in a whole frame (noise, half a frame) may be followed
        # by more: the next request then waits for the line to be quiet.
        self._dirty = bool(self._framer.pending) or \
            self.adapter.garbage_seen(self._framer) > garbage

    def _on_frame(self, frame: Any, now: float) -> None:
        if self._waiting is not None:
            exchange, future = self._waiting
            answer = exchange.match(frame)
            if answer is not None:
                if not future.done():
                    future.set_result(answer)
                return
        for s in self.sensors.values():
            answer = self.adapter.unsolicited(frame, s.config.series, s.address)
            if answer is None:
                continue
            if answer.values.get("done"):
                s.busy_until = now
                log.info("sensor %s: gyro calibration done", s.name)
                self.cache.set_state(s.name, busy=False)
                return
            if not s.config.stream_hz:
                # Left streaming by an earlier owner, say: it would collide with polls.
                self._stray(s, now)
            elif not s.streaming:
                s.streaming = True  # the stream is back by itself: stop polling it
                self.cache.set_state(s.name, streaming=True)
                log.info("sensor %s: its stream is back", s.name)
            s.last_stream = now
            self._publish(s, answer, now)
            self._stream_frame.set()
            return
        self.stats.errors["unexpected_frame"] += 1
        # Unasked-for frames from a sensor that should not stream: it streams something
        # (its default auto-output is the angles) and must be told to stop.  If it was a
        # late answer instead, "rate 0" is what it is set to anyway.
        sender = getattr(frame, "unit", getattr(frame, "address", None))
        for s in self.sensors.values():
            if s.address == sender and not s.config.stream_hz:
                self._stray(s, now)

    @staticmethod
    def _stray(s: Sensor, now: float) -> None:
        """An unasked-for frame from a sensor that should not stream."""
        s.stray_frames = [t for t in s.stray_frames if now - t < STRAY_WINDOW] + [now]
        if len(s.stray_frames) >= STRAY_EVIDENCE:
            s.stray_frames.clear()
            s.stop_stray_stream = True

    def _poll_of(self, s: Sensor) -> Exchange:
        """The sensor's poll, built once per address (it is sent hundreds of times a
        second; the time between an answer and the next request is the line's)."""
        poll = self._polls.get(s.name)
        if poll is None or poll[0] != s.address:
            poll = self._polls[s.name] = (s.address, self.adapter.poll(s.config.series,
                                                                       s.address))
        return poll[1]

    def _publish(self, s: Sensor, answer: Answer, at: float) -> None:
        reading = to_reading(answer.values, s.config.series)
        if reading is not None:
            self.cache.publish(s.name, reading, at)
            s.stats.readings += 1
            s.stats.rate.add(at)
            self._succeeded(s)
        # Whoever asked for a fresh reading has one now (from a poll or a stream frame).
        job = self._on_demand.pop(s.name, None)
        if job is not None and job.future is not None and not job.future.done():
            job.future.set_result(None)

    # ------------------------------------------------------------ scheduling

    def _housekeeping(self, now: float) -> None:
        for s in self.sensors.values():
            if s.streaming and now - s.last_stream > s.stream_timeout:
                s.streaming = False
                s.stream_retry_at = now + STREAM_RETRY
                s.next_due = now
                self.cache.set_state(s.name, streaming=False)
                log.warning("sensor %s: its stream stopped; polling it", s.name)
            if s.busy_until and now >= s.busy_until:
                s.busy_until = 0.0
                self.cache.set_state(s.name, busy=False)

    def _next_job(self, now: float) -> Job | None:
        while self._commands:
            job = self._commands.popleft()
            if job.sensor.busy_until > now:
                self._fail(job, ErrorKind.BUSY, f"{job.sensor.name} is busy for another "
                           f"{job.sensor.busy_until - now:.1f} s (save or calibration)")
                continue
            return job
        for s in self.sensors.values():
            if s.wants_stream(now):
                return Job(Priority.STREAM_SETUP, s)
            if s.stop_stray_stream and now >= s.stream_retry_at:
                s.stop_stray_stream, s.stream_retry_at = False, now + STREAM_RETRY
                log.warning("sensor %s: streams though stream_hz is 0; stopping it", s.name)
                return Job(Priority.STREAM_SETUP, s,
                           plan=self.adapter.stream_stop(s.config.series, s.address))
        for name, job in list(self._on_demand.items()):
            if job.sensor.busy_until > now:
                del self._on_demand[name]
                self._fail(job, ErrorKind.BUSY, f"{name} is busy (save or calibration)")
            elif not job.sensor.streaming and not job.started:
                job.started = True  # stays listed until answered, for later askers
                return job
        due = [s for s in self.sensors.values()
               if s.next_due <= now and s.busy_until <= now and not s.streaming]
        if due:
            return Job(Priority.POLL, min(due, key=lambda s: (s.next_due, s.last_served)))
        return None

    def _next_wake(self, now: float) -> float:
        times = [now + 1.0]
        for s in self.sensors.values():
            if s.busy_until > now:
                times.append(s.busy_until)
            elif s.streaming:
                times.append(s.last_stream + s.stream_timeout)
            else:
                times.append(s.next_due)
            if s.config.stream_hz and not s.streaming:
                times.append(s.stream_retry_at)
        return min(times)

    def _schedule_next_poll(self, s: Sensor, now: float) -> None:
        if s.failures:
            s.next_due = now + min(BACKOFF_MAX, BACKOFF_MIN * 2 ** (s.failures - 1))
        elif s.period == 0:
            s.next_due = now
        else:
            s.next_due += s.period
            if s.next_due < now - s.period:
                # Behind by more than a period: count the polls that will not happen
                # rather than firing a burst of catch-up reads.
                missed = int((now - s.next_due) / s.period)
                s.stats.missed_polls += missed
                s.next_due += missed * s.period
            s.next_due = max(s.next_due, now - s.period)

    # ------------------------------------------------------------ carrying out jobs

    async def _execute(self, job: Job) -> None:
        s = job.sensor
        now = self._now()
        try:
            match job.priority:
                case Priority.POLL | Priority.ON_DEMAND:
                    answer = await self._transact(s, self._poll_of(s))
                    if not answer.ok:  # a Modbus exception, or a frame that did not decode
                        self._count_error(s, "refused")
                        raise _Failed("refused")
                    self._succeeded(s)  # now: the next poll is scheduled before publishing
                    # Publishing (normalise, hand to the cache) waits until the next
                    # request is on the wire: call_soon runs at the loop's next turn,
                    # after this task has gone on to write it.
                    # (_publish also answers an on-demand job: it is listed until then.)
                    asyncio.get_running_loop().call_soon(self._publish, s, answer,
                                                         self._now())
                case Priority.STREAM_SETUP if job.plan is not None:
                    for exchange in job.plan:
                        await self._transact(s, exchange)
                case Priority.STREAM_SETUP:
                    await self._start_stream(s)
                case Priority.COMMAND if job.plan is not None:
                    assert job.future is not None
                    answer = await self._transact(s, job.plan[0])
                    self._succeeded(s)
                    if not job.future.done():
                        job.future.set_result(answer.values["pdu"])
                case Priority.COMMAND:
                    assert job.command is not None and job.future is not None
                    result = await self._command(s, job.command)
                    if not job.future.done():
                        job.future.set_result(result)
        except _Failed as exc:
            self._failed(s, exc.kind)
            kind = {"port_lost": ErrorKind.OFFLINE, "refused": ErrorKind.FAILURE}.get(
                exc.kind, ErrorKind.TIMEOUT)
            self._fail(job, kind, f"{s.name} did not answer ({exc.kind})")
            if job.priority is Priority.STREAM_SETUP:
                s.stream_retry_at = self._now() + STREAM_RETRY
        except LinkError as exc:  # e.g. the port refused a new baud rate
            self._on_lost(exc)
            self._fail(job, ErrorKind.OFFLINE, f"bus {self.name}: {exc}")
        except Exception:
            # A bug must cost one request, not the bus: log it, answer, carry on.
            log.exception("bus %s: error while serving %s", self.name, s.name)
            self._fail(job, ErrorKind.OFFLINE, "internal error in the gateway (logged)")
        finally:
            s.last_served = now
            if job.priority in (Priority.POLL, Priority.ON_DEMAND):
                self._schedule_next_poll(s, self._now())

    def _fail(self, job: Job, kind: ErrorKind, message: str) -> None:
        if self._on_demand.get(job.sensor.name) is job:
            del self._on_demand[job.sensor.name]
        future = job.future
        if future is None or future.done():
            return
        if job.command is not None:
            future.set_result(CommandResult.failed(job.sensor.name, job.command.name,
                                                   CommandError(kind, message)))
        else:
            future.set_exception(SensorUnavailable(kind, message))
            future.exception()  # retrieved here: a read nobody awaits any more is not an error

    async def _command(self, s: Sensor, command: Command) -> CommandResult:
        try:
            plan = self.adapter.command(s.config.series, s.address, command.name, command.args)
        except UsageError as exc:  # Unsupported, or a value the protocol cannot carry
            kind = ErrorKind.UNSUPPORTED if isinstance(exc, Unsupported) else \
                ErrorKind.BAD_ARGUMENTS
            return CommandResult.failed(s.name, command.name, CommandError(kind, str(exc)))
        answer: dict[str, Any] = {}
        for exchange in plan:
            result = await self._transact(s, exchange)
            if exchange.answer_bytes:  # a write nobody answers proves nothing about s
                self._succeeded(s)
            if not result.ok:
                return CommandResult(s.name, command.name, False, dict(result.values),
                                     f"{s.name}: {result.detail}", ErrorKind.FAILURE)
            self._apply(s, exchange.effect)
            answer.update(result.values)
        if command.name == "read_settings":
            answer["address"] = s.address
        log.info("sensor %s: %s %s done", s.name, command.name, dict(command.args) or "")
        return CommandResult(s.name, command.name, True, answer)

    async def _start_stream(self, s: Sensor) -> None:
        try:
            plan = self.adapter.stream_start(s.config.series, s.address, s.config.stream_hz)
        except UsageError as exc:
            log.error("sensor %s: cannot stream at %s Hz: %s", s.name, s.config.stream_hz, exc)
            s.stream_retry_at = float("inf")
            return
        for exchange in plan:
            result = await self._transact(s, exchange)
            if not result.ok:
                log.warning("sensor %s: refused auto-output: %s", s.name, result.detail)
                s.stream_retry_at = self._now() + STREAM_RETRY
                return
        s.streaming, s.last_stream = True, self._now()
        self._succeeded(s)
        self.cache.set_state(s.name, streaming=True)
        log.info("sensor %s: streaming at %s Hz", s.name, s.config.stream_hz)

    def _apply(self, s: Sensor, effect: Effect) -> None:
        now = self._now()
        if effect.new_baud is not None and effect.new_baud != self.baud:
            log.warning("bus %s: following %s from %d to %d baud", self.name, s.name, self.baud,
                        effect.new_baud)
            self.baud = effect.new_baud
            self.link.set_baudrate(effect.new_baud)
            if self.config.timeout_ms is None:  # derived from the rate: derive it again
                self.timeout = self.config.model_copy(
                    update={"baudrate": effect.new_baud}).effective_timeout_ms() / 1000
        if effect.new_address is not None and effect.new_address != s.address:
            log.warning("sensor %s: now at address %d (the config says %d)", s.name,
                        effect.new_address, s.config.address)
            s.address = effect.new_address
        if effect.busy_for or effect.busy_until_done:
            s.busy_until = now + (GYRO_CAL_SECONDS if effect.busy_until_done else effect.busy_for)
            self.cache.set_state(s.name, busy=True)

    def _succeeded(self, s: Sensor) -> None:
        s.failures = 0
        if s.online is not True:
            log.info("sensor %s: %s", s.name, "recovered" if s.online is False else "online")
            s.online = True
            self.cache.set_state(s.name, online=True)

    def _failed(self, s: Sensor, kind: str) -> None:
        s.failures += 1
        if kind == "port_lost":
            return
        if s.failures == OFFLINE_AFTER and s.online is not False:
            log.warning("sensor %s: offline (%s)", s.name,
                        "never answered" if s.online is None else kind)
            s.online = False
            self.cache.set_state(s.name, online=False)

    # ------------------------------------------------------------ one exchange

    async def _transact(self, s: Sensor, exchange: Exchange) -> Answer:
        """One request and its answer, with retries; raises ``_Failed``."""
        loop = asyncio.get_running_loop()
        kind = "timeout"
        for _attempt in range(self.config.retries + 1):
            gap = await self._clear_to_send(exchange)
            if not self.port_open:
                raise _Failed("port_lost")
            c = char_time(self.baud)
            request_time = len(exchange.request) * c
            future: asyncio.Future[Answer] = loop.create_future()
            self._waiting = (exchange, future)
            garbage = self.adapter.garbage_seen(self._framer)
            started = loop.time()
            try:
                self.link.write(exchange.request, exchange.answer_bytes)
                self._last_tx_end = started + request_time
                if exchange.answer_bytes == 0:
                    await asyncio.sleep(request_time)
                    answer = Answer({})
                else:
                    budget = request_time + exchange.answer_bytes * c + gap + self.timeout
                    # Not wait_for: it wakes this task one loop turn after the answer
                    # (through a waiter of its own), and that turn is line time.
                    timer = loop.call_later(budget, _time_out, future)
                    try:
                        answer = await future
                    finally:
                        timer.cancel()
            except LinkError as exc:
                self._on_lost(exc)
                raise _Failed("port_lost") from None
            except TimeoutError:
                kind = "bad_frame" if self.adapter.garbage_seen(self._framer) > garbage \
                    else "timeout"
                self._count_error(s, kind)
                self._flush_framer()
                # A late answer may still be on its way: do not talk over it.
                self._quiet_until = loop.time() + min(self.timeout, LATE_ANSWER_GRACE)
                continue
            finally:
                self._waiting = None
                # The silent gap before the request counts, but not twice: it starts
                # at the answer before, whose exchange was counted up to its end.
                end = loop.time()
                took = end - max(started - gap, self._busy_end)
                self._busy_end = end
                self.stats.busy_time += took
                s.stats.busy_time += took
            self.stats.transactions += 1
            s.stats.transactions += 1
            self.stats.rate.add(loop.time())
            self.stats.wire_time += (len(exchange.request) + exchange.answer_bytes) * c + \
                (2 * gap if exchange.answer_bytes else gap)
            return answer
        raise _Failed(kind)

    async def _clear_to_send(self, exchange: Exchange) -> float:
        """Wait until ``exchange`` may go out; returns the silent gap the protocol needs.

        After a whole answer the line is known to be quiet and only the protocol's gap
        applies.  After noise or half a frame it must have been quiet for at least 3.5
        characters and ``MIN_QUIET``; after a timeout, for a late answer's grace.  Next to a
        streaming sensor the exchange must also fit before its next frame; when it
        does not, it waits for a frame to end and goes in the pause after it.
        """
        c = char_time(self.baud)
        gap = self.adapter.gap_before_request(self.baud)
        quiet = max(gap, 3.5 * c, MIN_QUIET)
        streamer = next((s for s in self.sensors.values() if s.streaming), None)
        if streamer is not None:
            # Next to a fast stream, wait for a frame to end (at most one period).  Next
            # to a slow one that would hold every exchange to its rate, so go at once
            # when the exchange fits well before the next frame (its time is estimated
            # from when the last one was delivered, a few ms late: hence the margin).
            period = 1 / streamer.config.stream_hz
            needs = (len(exchange.request) + exchange.answer_bytes) * c + 2 * quiet
            fits = self._now() + needs + STREAM_MARGIN < streamer.last_stream + period
            if period < SLOW_STREAM or not fits:
                self._stream_frame.clear()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._stream_frame.wait(), 2 * period)
        while self.port_open:
            now = self._now()
            settle = quiet if self._dirty else gap
            ready_at = max(self._last_rx + settle, self._last_tx_end + gap, self._quiet_until)
            if now >= ready_at and not self._framer.pending:
                break
            if now >= self._last_rx + quiet and self._framer.pending:
                self._flush_framer()  # a half frame that stopped coming never completes
                continue
            await asyncio.sleep(max(ready_at - now, MIN_QUIET / 2))
        return gap

    def _count_error(self, s: Sensor, kind: str) -> None:
        self.stats.errors[kind] += 1
        s.stats.errors[kind] += 1
        self.cache.count_error(s.name)

    def _flush_framer(self) -> None:
        """After a timeout, a half frame in the framer will never complete."""
        now = self._now()
        while self._framer.pending:
            for frame in self._framer.expire():
                self._on_frame(frame, now)

    # ------------------------------------------------------------ shutdown

    async def _shutdown(self) -> None:
        self._fail_pending(ErrorKind.OFFLINE, "the gateway is stopping")
        if self.port_open:
            for s in self.sensors.values():
                if s.streaming:
                    # Leave the line quiet for the next owner: stop the auto-output.
                    with contextlib.suppress(_Failed, UsageError, LinkError):
                        for exchange in self.adapter.stream_stop(s.config.series, s.address):
                            await self._transact(s, exchange)
        self.port_open = False
        self.link.close()
        self._fail_pending(ErrorKind.OFFLINE, "the gateway is stopping")

    # ------------------------------------------------------------ views

    def sensor_stats(self, name: str) -> dict[str, Any]:
        s, now = self.sensors[name], self._now()
        return {
            "address": s.address,
            "transactions": s.stats.transactions,
            "readings": s.stats.readings,
            "errors": dict(s.stats.errors),
            "missed_polls": s.stats.missed_polls,
            "bus_share": round(s.stats.busy_time / max(now - self.stats.started, 1e-9), 4),
            "requested_hz": s.config.stream_hz if s.streaming else s.config.poll_hz,
            "achieved_hz": round(s.stats.rate.per_second(now), 2),
            "streaming": s.streaming,
            "online": bool(s.online),
        }

    def bus_stats(self) -> dict[str, Any]:
        now = self._now()
        return {
            "name": self.name,
            "port": self.config.port,
            "baudrate": self.baud,
            "protocol": self.config.protocol.name.lower(),
            "port_open": self.port_open,
            "transactions": self.stats.transactions,
            "errors": dict(self.stats.errors),
            "transactions_per_s": round(self.stats.rate.per_second(now), 2),
            "utilisation": round(self.stats.utilisation(now), 4),
            "busy_ms": round(self.stats.busy_time * 1000),
            "wire_utilisation": round(self.stats.wire_utilisation(now), 4),
            "queue_depth": self.queue_depth(),
        }


__all__ = ["BusMaster", "SensorUnavailable"]
