"""The bus master: the one owner of a serial line, and the driver of its schedule.

Every decision (what goes next, when, how long to wait, what a silence means) is the
``Schedule``'s, which is sans-IO.  This module only carries them out: it opens the
port and reopens it with back-off, writes the requests the schedule hands it, feeds
it the bytes that come in and the timer when it is due, and turns its events into
cache updates, log lines and the answers of whoever asked.

It runs on the bus thread as a client of its loop (``reactor``): the loop asks it
when it next needs a turn (``next_at``) and gives it one (``on_timer``); its port's
bytes come straight from the loop.  Everything here runs on that thread.  Whoever
asks for something (a command, a read, a pass-through) passes a ``Done`` callback,
called on the bus thread with the outcome or the error.

An answer's last byte is handed to the schedule the moment the loop has it, and the
next request is written right there, before the answer is normalised and published:
the time between an answer and the next request is the line's.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
import typing
from collections.abc import Callable, Mapping
from typing import TypeVar

from ..commands import CATALOGUE, Command, CommandResult
from ..config import BusConfig
from ..errors import ErrorKind, LinkError, RequestFailed
from ..model import KnownSettings, Reading
from ..normalise import to_reading
from ..protocol.exchanges import ModbusAdapter, adapter_for
from ..stats import BusStats, Counters, SensorStats, ms, share
from .events import (
    ErrorCounted,
    Event,
    Finished,
    Job,
    Kind,
    Note,
    Outcome,
    Publish,
    StateChange,
    Trace,
)
from .link import SerialLink
from .port import PortKeeper
from .reactor import Reactor
from .schedule import Schedule
from .sensor_state import OFFLINE_AFTER, SensorState
from .trace import TraceTap, Watcher

log = logging.getLogger("imu_gateway.bus")

#: The shortest wait for the schedule's timer: a guard against a spin, never a rule.
MIN_WAIT = 0.0001
#: After an internal error, the bus waits this long before it goes on.
BUG_PAUSE = 0.1
#: How often the counters are published while nothing else publishes them: the front
#: ends' rates and shares are at most this old.  (Before a command's answer or a state
#: change is passed on, they are published too: a client never sees the old address.)
STATS_EVERY = 0.25
T = TypeVar("T")
#: Told on the bus thread how a job ended: its outcome, or the error.
Done = Callable[[Outcome, RequestFailed | None], None]


class BusToCache(typing.Protocol):
    """What a bus master writes to the cache (``Cache`` itself, or a ``CacheWriter`` that
    hands the writes to another thread's loop)."""

    def publish(self, name: str, reading: Reading, at: float | None = None) -> object: ...

    def set_state(self, name: str, *, online: bool | None = None, busy: bool | None = None,
                  streaming: bool | None = None) -> None: ...

    def count_error(self, name: str) -> None: ...

    def learn(self, name: str, shown: KnownSettings) -> None: ...

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
        self.reactor: Reactor | None = None
        self._waiters: dict[Job, list[Done]] = {}
        # the turns it asks the loop for: the schedule's, the counters', the reopening's
        self._wake = self._stats_at = math.inf
        self._finished = False
        self.port = PortKeeper(self)
        # (--log-level debug: every bus's trace in the log)
        self.traces = TraceTap(self.name, config.trace or logging.getLogger(
            "imu_gateway").isEnabledFor(logging.DEBUG))
        self.schedule.trace(self.traces.wanted)
        self._swept: list[Callable[[], None]] = []  # told once removed sensors have left

    @property
    def sensors(self) -> dict[str, SensorState]:
        return self.schedule.sensors

    @property
    def stats(self) -> Counters:
        return self.schedule.stats

    @property
    def port_open(self) -> bool:
        return self.schedule.port_open

    @property
    def done(self) -> bool:
        """Stopped for good: the port closed, every job answered."""
        return self._finished

    # ------------------------------------------------------------ public interface
    # (on the bus thread; ``done`` is called there, once)

    def submit(self, sensor: str, command: Command, done: Done) -> None:
        """Carry out a validated command; ``done`` gets its ``CommandResult``."""
        if (refusal := self.schedule.refusal(sensor)) is not None:
            done(CommandResult.failed(sensor, command.name, refusal), None)
            return
        self._wait_for(self.schedule.command(sensor, command), done)

    def passthrough(self, sensor: str, pdu: bytes, done: Done) -> None:
        """A Modbus request PDU to the sensor unchanged, queued like a command; ``done``
        gets the sensor's answer PDU (its exceptions included), or ``RequestFailed``
        when it does not answer."""
        if (refusal := self.schedule.refusal(sensor)) is not None:
            done(None, refusal)
        elif not isinstance(self.adapter, ModbusAdapter):
            done(None, RequestFailed(ErrorKind.UNSUPPORTED, f"{sensor} does not speak Modbus"))
        else:
            exchange = self.adapter.raw(self.sensors[sensor].address, pdu)
            self._wait_for(self.schedule.passthrough(sensor, exchange), done)

    def read_now(self, sensor: str, done: Done) -> None:
        """Read the sensor now (behind commands).  Concurrent calls share one exchange;
        a streaming sensor's next frame serves them.  ``done`` gets None, or
        ``RequestFailed``."""
        if (refusal := self.schedule.refusal(sensor, queued=False)) is not None:
            done(None, refusal)
            return
        job, new = self.schedule.read(sensor)
        self._waiters.setdefault(job, []).append(done)
        if new:
            self.poke()

    def _wait_for(self, job: Job, done: Done) -> None:
        self._waiters[job] = [done]
        self.poke()

    def stop(self) -> None:
        """Finish the exchange in flight, stop the streams, then stop."""
        self.schedule.stop(self.now())
        self.dispatch()
        self.poke()

    def watch(self, watcher: Watcher, on: bool = True) -> None:
        """Tell ``watcher`` every exchange from now on (a traffic monitor), or no more
        (``on`` False)."""
        self.traces.watch(watcher, on)
        self.schedule.trace(self.traces.wanted)

    def change_sensors(self, config: BusConfig, done: Callable[[], None]) -> None:
        """A reload: from now on the bus's sensors are ``config``'s (its own settings
        are the same).  New ones join the schedule, gone ones leave it once nothing of
        theirs is in flight (``Schedule.remove``); the port stays open and the others go
        on untouched.  ``done`` is called once the gone ones have left, after the
        counters (which name the new ones) were published."""
        now = self.now()
        wanted = {s.name: s for s in config.sensors}
        for name, state in list(self.sensors.items()):
            if name not in wanted and not state.leaving:
                self.schedule.remove(name, now)
        for name, sensor in wanted.items():
            if name not in self.sensors or self.sensors[name].leaving:
                self.schedule.add(sensor, now)
        self.config = config
        self._swept.append(done)
        self.dispatch()
        self.poke()

    # ------------------------------------------------------------ the loop's client

    def start(self, reactor: Reactor) -> None:
        """Join the bus thread's loop (called on that thread)."""
        self.reactor = reactor
        now = self.now()
        self.schedule.start(now)
        self._stats_at = now + STATS_EVERY
        self.port.reopen_at = now
        reactor.clients.append(self)

    def next_at(self) -> float:
        return min(self._wake, self._stats_at, self.port.reopen_at, self.link.rest_at)

    def on_timer(self, now: float) -> None:
        if self.link.rest_at <= now:
            self.link.on_timer(now)  # the rest of an answer: on to on_bytes
        if self._stats_at <= now:
            self._stats_at = now + STATS_EVERY
            self._publish_stats()
        if self.port.reopen_at <= now:
            self.port.reopen_at = math.inf
            self.port.open()
        if self._wake <= now:
            self.turn()

    def turn(self, drained: bool = False) -> None:
        """Deadlines, the next request, the events; then when the next turn is due.
        ``drained``: the port was read empty just now (no need to ask it)."""
        self._wake = math.inf
        if self._finished or not (self.port_open or self.schedule.stopping):
            return  # the port is (re)opening: its end gives the next turn
        wake = self._guarded(lambda: self._step(drained))
        if self.schedule.finished:
            self.finish()
            return
        now = self.now()
        self._wake = max(wake if wake is not None else now + BUG_PAUSE, now + MIN_WAIT)

    def _step(self, drained: bool = False) -> float:
        """The timer's turn: deadlines, the next request, the events; when to wake."""
        now = self.now()
        # (asked once: bytes reach the schedule only through on_bytes, after this; not
        # after a read took all there was, nor when nothing decided now depends on it:
        # an ioctl is a tenth of an exchange's CPU)
        pending = 0 if drained or not self.schedule.needs_pending() else self.link.pending()
        self.schedule.handle_timer(now, pending)
        self._send(now, pending)
        wake = self.schedule.next_wake(self.now(), pending)
        self.dispatch()  # (next_wake may have flushed a half frame: its events too)
        return wake

    def finish(self) -> None:
        """Stop for good now, whatever is in flight (the end of a stop, or past its
        grace)."""
        if self._finished:
            return
        self._finished = True
        self._wake = self._stats_at = self.port.reopen_at = math.inf
        self.link.close()
        self.schedule.close(self.now(), "the gateway is stopping")
        self.dispatch()
        self._publish_stats()

    def _guarded(self, step: Callable[[], T]) -> T | None:
        """A bug must cost one request, not the bus: logged, the job in flight answered
        as failed, and the bus carries on."""
        try:
            return step()
        except Exception:
            log.exception("bus %s: internal error; the request in flight is dropped",
                          self.name)
            with contextlib.suppress(Exception):
                self.schedule.abort(self.now(), "internal error in the gateway (logged)")
                self.dispatch()
            return None

    @staticmethod
    def now() -> float:
        return time.monotonic()

    def poke(self) -> None:
        """Something changed (a job queued, a stop, the port lost): a turn at once."""
        self._wake = 0.0

    # ------------------------------------------------------------ bytes in, bytes out

    def on_bytes(self, data: bytes, at: float) -> None:
        """From the link, on the bus thread; ``at``: when the bytes came in.  The turn
        that follows sends the next request before the answer is published."""
        self._guarded(lambda: self.schedule.receive(data, at))
        self.turn(drained=self.link.watched)

    def _send(self, now: float, pending: int) -> None:
        request = self.schedule.next_request(now, pending)
        if request is None:
            return
        try:
            if self.link.baudrate != self.schedule.baud:
                # A command moved the line (native: after its answer at the old rate).
                log.warning("bus %s: port now at %d baud", self.name, self.schedule.baud)
                self.link.set_baudrate(self.schedule.baud)
            if not self.link.write(request.data, request.expect, request.look_after,
                                   request.latest):
                # Kept from writing past the place next to a stream the request was
                # given (a busy machine): it goes back, and waits for the next place.
                self.schedule.withdraw()
                return
            self.schedule.written(self.now())  # held in the write, it left by then
        except LinkError as exc:
            self.port.lost(exc)

    def dispatch(self) -> None:
        """Carry out what the schedule says happened, in order.  A state change or a
        job's end is passed on after the counters: whoever it wakes reads them new."""
        events = self.schedule.take_events()
        if events and any(isinstance(e, _PASSED_ON) for e in events):
            self._publish_stats()
        for event in events:
            try:
                _carry_out(self, event)
            except Exception:  # one event's failure must not lose the others
                log.exception("bus %s: internal error carrying out %s", self.name, event)
        if self._swept and not self.schedule.leaving:
            self._publish_stats()
            swept, self._swept = self._swept, []
            for done in swept:
                done()

    def _resolve(self, job: Job, outcome: Outcome, error: RequestFailed | None) -> None:
        # (each job's error is its own: made when it ended)
        for done in self._waiters.pop(job, ()):
            done(outcome, error)

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
        return sensor_stats_of(self, name, self.now())

    def bus_stats(self) -> BusStats:
        return bus_stats_of(self, self.now())


def _carry_out(master: BusMaster, event: Event) -> None:
    """One event of the schedule, carried out: the cache, the log, whoever asked."""
    match event:
        case Publish(name, answer, at):
            state = master.sensors.get(name)
            if state is None:
                return  # (a removed sensor's last answer: it is no longer the bus's)
            reading = to_reading(answer.values, state.config.series)
            if reading is not None:
                master.cache.publish(name, reading, at)
                master.schedule.count_reading(name, at)
        case StateChange(name, online, busy, streaming):
            master.cache.set_state(name, online=online, busy=busy, streaming=streaming)
        case ErrorCounted(name):
            master.cache.count_error(name)
        case Finished(job, outcome, error):
            if (shown := _learned(job, outcome)) is not None:
                master.cache.learn(job.sensor.name, shown)
            master._resolve(job, outcome, error)
        case Note(level, text):
            log.log(level, "%s", text)
        case Trace():
            master.traces.write(event, master.now())


#: Events passed on after the counters (``dispatch``).
_PASSED_ON = (StateChange, Finished)


def _learned(job: Job, outcome: Outcome) -> KnownSettings | None:
    """The settings a read the bus asked for itself (after an absence) found: nobody
    else is there to learn them."""
    if job.kind is Kind.SETTINGS and isinstance(outcome, CommandResult) and outcome.ok:
        return CATALOGUE["read_settings"].learns({}, outcome.answer)
    return None


def sensor_stats_of(master: BusMaster, name: str, now: float) -> SensorStats:
    """A sensor's counters, frozen (on the bus's thread)."""
    s = master.sensors[name]
    timer = s.timer
    return SensorStats(
        address=s.address, online=bool(s.online), streaming=s.streaming,
        transactions=s.stats.transactions, readings=s.stats.readings,
        errors=dict(s.stats.errors), missed_polls=s.stats.missed_polls,
        late_answers=s.stats.late_answers, early_answers=s.stats.early_answers,
        stream_stops=s.stats.stream_stops,
        bus_share=share(s.stats.busy_time, now - master.schedule.started),
        requested_hz=s.config.stream_hz if s.streaming else s.config.poll_hz,
        achieved_hz=round(s.stats.rate.per_second(now), 2),
        latency_ms=ms(timer.srtt), latency_dev_ms=ms(timer.rttvar if timer.samples else None),
        timeout_ms=ms(timer.rto) or 0.0)


def bus_stats_of(master: BusMaster, now: float) -> BusStats:
    """The bus's counters, frozen (on the bus's thread)."""
    stats = master.stats
    elapsed = now - master.schedule.started
    return BusStats(
        name=master.name, port=master.config.port, baudrate=master.schedule.baud,
        protocol=master.config.protocol.name.lower(), port_open=master.port_open,
        transactions=stats.transactions, errors=dict(stats.errors),
        late_answers=stats.late_answers, early_answers=stats.early_answers,
        late_writes=stats.late_writes, transactions_per_s=round(stats.rate.per_second(now), 2),
        utilisation=share(stats.busy_time, elapsed), busy_ms=round(stats.busy_time * 1000),
        wire_utilisation=share(stats.wire_time, elapsed),
        queue_depth=master.schedule.queue_depth())


__all__ = ["OFFLINE_AFTER", "BusMaster", "Done"]
