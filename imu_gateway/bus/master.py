"""The bus master: the one owner of a serial line, and the driver of its schedule.

Every decision (what goes next, when, how long to wait, what a silence means) is the
``Schedule``'s, which is sans-IO.  This module only carries them out: it opens the
port and reopens it with back-off, writes the requests the schedule hands it, feeds
it the bytes that come in and the timer when it is due, and turns its events into
cache updates, log lines and the answers of whoever asked.

An answer's last byte is handed to the schedule the moment the serial reader has it,
and the next request is written right there, before the answer is normalised and
published: the time between an answer and the next request is the line's.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import typing
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from ..commands import Command, CommandResult
from ..config import BusConfig
from ..errors import ErrorKind, LinkError, RequestFailed
from ..model import Reading
from ..normalise import to_reading
from ..protocol.exchanges import ModbusAdapter, adapter_for
from ..stats import BusStats, Counters, SensorStats, ms, share
from .events import ErrorCounted, Event, Finished, Job, Note, Publish, StateChange, Trace
from .link import SerialLink
from .schedule import Schedule
from .sensor_state import OFFLINE_AFTER, SensorState
from .trace import TraceLog

log = logging.getLogger("imu_gateway.bus")

REOPEN_MIN, REOPEN_MAX = 0.5, 5.0  # seconds between tries to reopen a lost port
#: The shortest wait for the schedule's timer: a guard against a spin, never a rule.
MIN_WAIT = 0.0001
#: After an internal error, the bus waits this long before it goes on.
BUG_PAUSE = 0.1
#: How often the counters are published while nothing else publishes them: the front
#: ends' rates and shares are at most this old.  (Before a command's answer or a state
#: change is passed on, they are published too: a client never sees the old address.)
STATS_EVERY = 0.25
T = TypeVar("T")


class BusToCache(typing.Protocol):
    """What a bus master writes to the cache (``Cache`` itself, or a ``CacheWriter`` that
    hands the writes to another thread's loop)."""

    def publish(self, name: str, reading: Reading, at: float | None = None) -> object: ...

    def set_state(self, name: str, *, online: bool | None = None, busy: bool | None = None,
                  streaming: bool | None = None) -> None: ...

    def count_error(self, name: str) -> None: ...

    def note_stats(self, bus: BusStats, sensors: Mapping[str, SensorStats]) -> None: ...


class BusMaster:
    def __init__(self, config: BusConfig, cache: BusToCache,
                 link: SerialLink | None = None) -> None:
        self.config = config
        self.name = config.name
        self.adapter = adapter_for(config.protocol)
        self.schedule = Schedule(config, self.adapter)
        self.link = link or SerialLink(config.port, config.baudrate, rs485=config.rs485)
        self.cache = cache
        self._futures: dict[Job, asyncio.Future[Any]] = {}
        self._waiter: asyncio.Future[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reopen_delay = REOPEN_MIN
        self._port_problem_logged = False
        self.trace_log = TraceLog(self.name)
        if logging.getLogger("imu_gateway").isEnabledFor(logging.DEBUG):
            self.schedule.outcomes.tracing = True  # --log-level debug: every bus

    @property
    def sensors(self) -> dict[str, SensorState]:
        return self.schedule.sensors

    @property
    def stats(self) -> Counters:
        return self.schedule.stats

    @property
    def port_open(self) -> bool:
        return self.schedule.port_open

    # ------------------------------------------------------------ public interface

    async def submit(self, sensor: str, command: Command) -> CommandResult:
        """Carry out a validated command; returns after the sensor's answer."""
        if (refusal := self.schedule.refusal(sensor)) is not None:
            return CommandResult.failed(sensor, command.name, refusal)
        result: CommandResult = await self._wait_for(self.schedule.command(sensor, command))
        return result

    async def passthrough(self, sensor: str, pdu: bytes) -> bytes:
        """A Modbus request PDU to the sensor unchanged, queued like a command; returns
        the sensor's answer PDU (its exceptions included).  Raises ``RequestFailed``
        when it does not answer."""
        if (refusal := self.schedule.refusal(sensor)) is not None:
            raise refusal
        if not isinstance(self.adapter, ModbusAdapter):
            raise RequestFailed(ErrorKind.UNSUPPORTED, f"{sensor} does not speak Modbus")
        exchange = self.adapter.raw(self.sensors[sensor].address, pdu)
        answer: bytes = await self._wait_for(self.schedule.passthrough(sensor, exchange))
        return answer

    async def read_now(self, sensor: str) -> None:
        """Read the sensor now (behind commands).  Concurrent calls share one exchange;
        a streaming sensor's next frame serves them.  Raises ``RequestFailed``."""
        if (refusal := self.schedule.refusal(sensor, queued=False)) is not None:
            raise refusal
        job, new = self.schedule.read(sensor)
        if new:
            self._futures[job] = asyncio.get_running_loop().create_future()
            self._poke()
        await asyncio.shield(self._futures[job])

    async def _wait_for(self, job: Job) -> Any:
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._futures[job] = future
        self._poke()
        return await future

    def stop(self) -> None:
        """Finish the exchange in flight, stop the streams, then stop."""
        self.schedule.stop(self._now())
        self._dispatch()
        self._poke()

    def queue_depth(self) -> int:
        return self.schedule.queue_depth()

    # ------------------------------------------------------------ the loop

    async def run(self) -> None:
        self._loop = loop = asyncio.get_running_loop()
        started = loop.time()
        self.schedule.started = self.stats.rate.started = started
        for s in self.sensors.values():
            s.stats.rate.started = started
        ticker = _Ticker(loop, STATS_EVERY, self._publish_stats)
        try:
            while not self.schedule.finished:
                if not self.port_open and not self.schedule.stopping:
                    await self._open_port()
                    continue
                wake = self._guarded(self._step)
                await self._sleep_until(wake if wake is not None else loop.time() + BUG_PAUSE)
        finally:
            ticker.cancel()
            self.link.close()
            self.schedule.port_open = False
            self.schedule.abort(self._now(), "the gateway is stopping")
            self.schedule.fail_pending(ErrorKind.OFFLINE, "the gateway is stopping")
            self._dispatch()
            self._publish_stats()

    def _step(self) -> float:
        """The timer's turn: deadlines, the next request, the events; when to wake."""
        assert self._loop is not None
        now = self._loop.time()
        # (asked once: the bytes reach the schedule only through _on_bytes, after this)
        pending = self.link.pending()
        self.schedule.handle_timer(now, pending)
        self._send(now, pending)
        wake = self.schedule.next_wake(self._loop.time(), pending)
        self._dispatch()  # (next_wake may have flushed a half frame: its events too)
        return wake

    def _guarded(self, step: Callable[[], T]) -> T | None:
        """A bug must cost one request, not the bus: logged, the job in flight answered
        as failed, and the bus carries on."""
        try:
            return step()
        except Exception:
            log.exception("bus %s: internal error; the request in flight is dropped",
                          self.name)
            with contextlib.suppress(Exception):
                self.schedule.abort(self._now(), "internal error in the gateway (logged)")
                self._dispatch()
            return None

    def _now(self) -> float:
        return self._loop.time() if self._loop is not None else 0.0

    async def _sleep_until(self, when: float) -> None:
        """Until ``when``, or until bytes, a request or a stop wake us (``_poke``)."""
        assert self._loop is not None
        waiter = self._waiter = self._loop.create_future()
        timer = self._loop.call_at(max(when, self._loop.time() + MIN_WAIT), _wake, waiter)
        try:
            await waiter
        finally:
            timer.cancel()
            self._waiter = None

    def _poke(self) -> None:
        if self._waiter is not None:
            _wake(self._waiter)

    # ------------------------------------------------------------ the port

    async def _open_port(self) -> None:
        try:
            await self.link.open(self._on_bytes, self._on_lost)
            self.link.set_baudrate(self.schedule.baud)
        except LinkError as exc:
            self.link.close()
            if not self._port_problem_logged:
                log.warning("bus %s: %s; retrying", self.name, exc)
                self._port_problem_logged = True
            self.schedule.lost(self._now(), str(exc))
            self._dispatch()
            await self._sleep_until(self._now() + self._reopen_delay)
            self._reopen_delay = min(self._reopen_delay * 2, REOPEN_MAX)
            return
        if self._port_problem_logged:
            log.warning("bus %s: port %s is back", self.name, self.config.port)
        else:
            log.info("bus %s: port %s open at %d baud", self.name, self.config.port,
                     self.schedule.baud)
        self._port_problem_logged = False
        self._reopen_delay = REOPEN_MIN
        self.schedule.open(self._now())

    def _on_lost(self, exc: Exception) -> None:
        """The port is gone (reported by the reader or by a failed write): once."""
        if not self.port_open:
            return
        self.link.close()
        log.warning("bus %s: port %s lost (%s); reopening", self.name, self.config.port, exc)
        self._port_problem_logged = True
        self.schedule.lost(self._now(), str(exc))
        self._dispatch()
        self._poke()

    # ------------------------------------------------------------ bytes in, bytes out

    def _on_bytes(self, data: bytes, at: float) -> None:
        """From the serial reader, in this loop; ``at``: when the bytes came in."""
        self._guarded(lambda: self._received(data, at))
        self._poke()  # the timer to wait for has changed

    def _received(self, data: bytes, at: float) -> None:
        self.schedule.receive(data, at)
        self._send(self._now(), self.link.pending())  # the next request first: publishing can wait
        self._dispatch()

    def _send(self, now: float, pending: int) -> None:
        request = self.schedule.next_request(now, pending)
        if request is None:
            return
        try:
            if self.link.baudrate != self.schedule.baud:
                # A command moved the line (native: after its answer at the old rate).
                log.warning("bus %s: port now at %d baud", self.name, self.schedule.baud)
                self.link.set_baudrate(self.schedule.baud)
            if self._now() > request.latest:
                # Kept from writing past the place next to a stream the request was
                # given (a busy machine): it goes back, and waits for the next place.
                self.schedule.withdraw()
                return
            self.link.write(request.data, request.expect)
            self.schedule.written(self._now())  # held in the write, it left by then
        except LinkError as exc:
            self._on_lost(exc)

    def _dispatch(self) -> None:
        """Carry out what the schedule says happened, in order.  A state change or a
        job's end is passed on after the counters: whoever it wakes reads them new."""
        events = self.schedule.take_events()
        if any(isinstance(e, StateChange | Finished) for e in events):
            self._publish_stats()
        for event in events:
            try:
                self._carry_out(event)
            except Exception:  # one event's failure must not lose the others
                log.exception("bus %s: internal error carrying out %s", self.name, event)

    def _carry_out(self, event: Event) -> None:
        match event:
            case Publish(name, answer, at):
                reading = to_reading(answer.values, self.sensors[name].config.series)
                if reading is not None:
                    self.cache.publish(name, reading, at)
                    self.sensors[name].stats.readings += 1
                    self.sensors[name].stats.rate.add(at)
            case StateChange(name, online, busy, streaming):
                self.cache.set_state(name, online=online, busy=busy, streaming=streaming)
            case ErrorCounted(name):
                self.cache.count_error(name)
            case Finished(job, outcome, error):
                self._resolve(job, outcome, error)
            case Note(level, text):
                log.log(level, "%s", text)
            case Trace():
                self.trace_log.write(event, self._now())

    def _resolve(self, job: Job, outcome: Any, error: RequestFailed | None) -> None:
        future = self._futures.pop(job, None)
        if future is None or future.done():
            return
        if error is None:
            future.set_result(outcome)
            return
        future.set_exception(error)  # (each job's error is its own: made when it ended)
        future.exception()  # retrieved here: a read nobody awaits any more is not an error

    # ------------------------------------------------------------ views

    def _publish_stats(self) -> None:
        try:
            self.cache.note_stats(*self.stats_snapshot())
        except Exception:  # counters must never cost the bus an exchange
            log.exception("bus %s: internal error publishing its counters", self.name)

    def stats_snapshot(self) -> tuple[BusStats, dict[str, SensorStats]]:
        """The bus's and its sensors' counters, frozen (made on the bus's thread)."""
        return self.bus_stats(), {name: self.sensor_stats(name) for name in self.sensors}

    def sensor_stats(self, name: str) -> SensorStats:
        s, now = self.sensors[name], self._now()
        timer = s.timer
        return SensorStats(
            address=s.address, online=bool(s.online), streaming=s.streaming,
            transactions=s.stats.transactions, readings=s.stats.readings,
            errors=dict(s.stats.errors), missed_polls=s.stats.missed_polls,
            late_answers=s.stats.late_answers, stream_stops=s.stats.stream_stops,
            bus_share=share(s.stats.busy_time, now - self.schedule.started),
            requested_hz=s.config.stream_hz if s.streaming else s.config.poll_hz,
            achieved_hz=round(s.stats.rate.per_second(now), 2),
            latency_ms=ms(timer.srtt), latency_dev_ms=ms(timer.rttvar if timer.samples else None),
            timeout_ms=ms(timer.rto) or 0.0)

    def bus_stats(self) -> BusStats:
        now, stats = self._now(), self.stats
        elapsed = now - self.schedule.started
        return BusStats(
            name=self.name, port=self.config.port, baudrate=self.schedule.baud,
            protocol=self.config.protocol.name.lower(), port_open=self.port_open,
            transactions=stats.transactions, errors=dict(stats.errors),
            late_answers=stats.late_answers,
            transactions_per_s=round(stats.rate.per_second(now), 2),
            utilisation=share(stats.busy_time, elapsed), busy_ms=round(stats.busy_time * 1000),
            wire_utilisation=share(stats.wire_time, elapsed), queue_depth=self.queue_depth())


class _Ticker:
    """``callback`` every ``interval`` seconds on ``loop``, until cancelled."""

    def __init__(self, loop: asyncio.AbstractEventLoop, interval: float,
                 callback: Callable[[], None]) -> None:
        self.loop, self.interval, self.callback = loop, interval, callback
        self.handle = loop.call_later(interval, self._tick)

    def _tick(self) -> None:
        self.callback()
        self.handle = self.loop.call_later(self.interval, self._tick)

    def cancel(self) -> None:
        self.handle.cancel()


def _wake(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


__all__ = ["OFFLINE_AFTER", "BusMaster"]
