"""The bus masters' side of the main loop: the bus thread, and a handle per bus.

The lines' timing must not depend on what the front ends are doing: with a hundred
Modbus TCP clients on the main event loop, each turn of that loop runs a long burst of
their callbacks, and a bus master sharing the loop would send each next request that
much later (measured: the bus rate fell by a third, ``docs/benchmarks.md``).  So the
bus masters run on a thread of their own, in one ``select()`` loop (``reactor``): one
thread carries every line of the process (8 lines at 115200 baud on a 2-core machine,
measured in ``bench/lines.py``).

The masters write to the cache through one ``CacheWriter``, which gathers what one
turn of the bus loop wrote (every line's) and hands it to the loop that owns the cache
in one piece, in order, so cache listeners (the front ends) always run there.  How soon
depends on who listens (``Cache.prompt``):

* a turn that answers someone waiting (a command, a fresh read, the traffic monitor):
  the main loop is woken at once;
* a listener that pushes to the outside (MQTT, Sparkplug, an SSE stream): the main
  loop is woken at most once per turn, or, with ``hand_over_ms`` (``window``), at
  most once in that time (the turns in between join: a fifth less CPU on a small box,
  for that much more latency to those listeners; a reader takes them at once,
  ``Cache.catch_up``); and not again while a hand-over it has not run yet is waiting:
  later turns join that one;
* otherwise (only Modbus TCP, REST and OPC UA, whose clients read, and whose
  subscriptions publish and sample, at their own times): the turns wait, and the main
  loop takes them when something reads the cache (``Cache.catch_up``), or after
  ``LAZY_HAND_OVER`` at the latest (history, alarms, captures), timed by the bus
  thread, which then wakes the main loop once.  A wake-up of the main loop costs more
  CPU than the work it brings: on one native line, the main loop's CPU per exchange
  went from 0.12-0.13 ms to 0.07-0.08, the process's from 0.35-0.39 to 0.26-0.27
  (``docs/benchmarks.md``, "The lazy hand-over").

Counters travel the same way, as frozen snapshots made on the bus thread
(``BusMaster.stats_snapshot``), and so do the answers of whoever asked (after the
counters they may read).  The front ends never touch a master's state.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from ..cache import Cache
from ..commands import Command, CommandResult
from ..config import BusConfig
from ..errors import ErrorKind, RequestFailed
from ..model import KnownSettings, Reading
from ..stats import BusStats, SensorStats, Trace
from .events import Outcome
from .frames import Frame, RecordingLink
from .master import BusMaster, Done
from .reactor import Reactor

log = logging.getLogger("imu_gateway.bus")
T = TypeVar("T")


#: The longest a turn's writes wait for the main loop when nobody needs them at once
#: (``CacheWriter``); readers catch up at once.  The main loop's staleness watch reads
#: the cache every ``app.STALENESS_TICK`` (0.1 s), so history, alarms and captures lag
#: by that much, and this is the bound when that watch is late: a hand-over of its own
#: every 50 ms was a wake-up of the main loop that the watch's made needless (on one
#: Modbus line 24 -> 13 a second).
LAZY_HAND_OVER = 0.25


class CacheWriter:
    """The cache's write side, used from the bus thread: the writes of one turn of the
    bus loop go to the cache's loop together, in order (``flush``), at once or lazily
    (the module's docstring)."""

    def __init__(self, cache: Cache) -> None:
        self.cache = cache
        self.loop: asyncio.AbstractEventLoop | None = None  # the cache's loop, set at start
        self._batch: list[Callable[[], None]] = []
        self._urgent = False  # the turn answers someone waiting: handed over at once
        # turns' writes handed over and not run yet, and whether the cache's loop has
        # been asked to run them (both shared with that loop: deque and bool are safe to
        # use from two threads under the GIL)
        self._out: deque[list[Callable[[], None]]] = deque()
        self._asked = False
        # (the bus thread's own) since when turns have waited lazily, unasked
        self._waiting_since: float | None = None
        #: (``hand_over_ms``, s) the longest a prompt turn waits: 0, none (set from the
        #: main loop: a float is read whole)
        self.window = 0.0
        self._asked_at = -math.inf  # (the bus thread's own) when it last asked
        cache.add_source(self._drain)

    def hand(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        """Run ``fn`` on the cache's loop, after everything handed before it."""
        self._batch.append(functools.partial(fn, *args, **kwargs))

    def hand_urgent(self, fn: Callable[..., Any], *args: Any) -> None:
        """``hand``, for someone waiting: the turn is handed over at once."""
        self._urgent = True
        self.hand(fn, *args)

    def flush(self) -> None:
        """Hand the turn's writes over (the bus loop calls this after each turn, and at
        ``next_at`` at the latest).  A lazy turn's wait is timed here, on the bus
        thread: the main loop is not woken to arm a timer of its own."""
        if self.loop is None:
            return
        urgent = False
        if self._batch:
            if not self._out:  # (a reader took what waited: the wait starts again)
                self._waiting_since = None
            self._out.append(self._batch)
            self._batch = []
            urgent, self._urgent = self._urgent, False
        if self._asked or not self._out:  # (a reader may have taken them all)
            self._waiting_since = None
        elif urgent:
            self._ask()
        elif self.cache.prompt:
            now = time.monotonic()
            if now >= self._asked_at + self.window:
                self._ask(now)
            else:  # (within the window: ``next_at`` is its end)
                self._waiting_since = self._asked_at + self.window - LAZY_HAND_OVER
        elif self._waiting_since is None:
            self._waiting_since = time.monotonic()
        elif time.monotonic() - self._waiting_since >= LAZY_HAND_OVER:
            self._ask()

    def next_at(self) -> float:
        """When the bus loop must turn to hand waiting turns over (``flush``): lazy
        ones, or prompt ones at the end of the window."""
        since = self._waiting_since
        return math.inf if since is None else since + LAZY_HAND_OVER

    def _ask(self, now: float | None = None) -> None:
        self._asked, self._waiting_since = True, None
        self._asked_at = time.monotonic() if now is None else now
        with contextlib.suppress(RuntimeError):  # the main loop closed: the process ends
            assert self.loop is not None
            self.loop.call_soon_threadsafe(self._run)

    def _run(self) -> None:
        """On the cache's loop: the turns handed over by now, in order.  (The flag is
        cleared first: a turn handed over from now on asks again, so none waits.)"""
        self._asked = False
        self.cache.catch_up()

    def _drain(self) -> None:
        """(``Cache.catch_up``'s source) Only the turns here now: those handed over
        meanwhile have asked again, and the loop's other work (sockets, timers) goes
        first, however busy the lines."""
        for _ in range(len(self._out)):
            _run_all(self._out.popleft())

    def publish(self, name: str, reading: Reading, at: float | None = None) -> None:
        self.hand(self.cache.publish, name, reading, at)

    def set_state(self, name: str, *, online: bool | None = None, busy: bool | None = None,
                  streaming: bool | None = None) -> None:
        self.hand(self.cache.set_state, name, online=online, busy=busy, streaming=streaming)

    def count_error(self, name: str) -> None:
        self.hand(self.cache.count_error, name)

    def learn(self, name: str, shown: KnownSettings) -> None:
        self.hand(self.cache.learn, name, shown)

    def note_stats(self, bus: BusStats, sensors: Mapping[str, SensorStats]) -> None:
        self.hand(self.cache.note_stats, bus, sensors)


def _run_all(batch: list[Callable[[], None]]) -> None:
    for fn in batch:
        try:
            fn()
        except Exception:  # one listener's failure must not lose the rest of the turn
            log.exception("internal error handing a bus's update to the cache")


def _settle(future: asyncio.Future[Outcome], outcome: Outcome,
            error: RequestFailed | None) -> None:
    if future.done():
        return  # the asker has gone (cancelled)
    if error is None:
        future.set_result(outcome)
    else:
        future.set_exception(error)


class BusRunner:
    """One bus master, as the main loop sees it: its calls go to the bus thread, and
    their answers come back to the caller's loop."""

    def __init__(self, config: BusConfig, writer: CacheWriter, reactor: Reactor) -> None:
        self.reactor = reactor
        self.writer = writer
        self.master = BusMaster(config, writer)
        # the counters as they are before the thread runs (read here, while no other
        # thread touches them): the front ends never see a bus without any
        writer.cache.note_stats(*self.master.stats_snapshot())

    def start(self) -> None:
        """Join the bus thread (started by the caller)."""
        self.reactor.post(functools.partial(self.master.start, self.reactor))

    def _not_running(self) -> RequestFailed:
        return RequestFailed(ErrorKind.OFFLINE, f"bus {self.master.name} is not running")

    async def call(self, fn: Callable[[], T]) -> T:
        """``fn()`` on the bus thread.  Raises ``RequestFailed`` when the bus thread is
        not running (not started, or stopped)."""
        if not self.reactor.running:
            raise self._not_running()
        return await asyncio.wrap_future(self.reactor.call(fn))

    async def _job(self, start: Callable[[Done], None]) -> Outcome:
        """Start a job on the bus thread; its outcome, after the cache writes before it."""
        if not self.reactor.running:
            raise self._not_running()
        future: asyncio.Future[Outcome] = asyncio.get_running_loop().create_future()

        def done(outcome: Outcome, error: RequestFailed | None) -> None:
            self.writer.hand_urgent(_settle, future, outcome, error)

        def begin() -> None:
            try:
                start(done)
            except Exception:  # a bug before the job was queued: its asker is answered
                log.exception("bus %s: internal error starting a request", self.master.name)
                done(None, RequestFailed(ErrorKind.FAILURE,
                                         "internal error in the gateway (logged)"))

        if not self.reactor.post(begin):
            raise self._not_running()  # it ended after the check above
        return await future

    async def submit(self, sensor: str, command: Command) -> CommandResult:
        result = await self._job(functools.partial(self.master.submit, sensor, command))
        assert isinstance(result, CommandResult)  # (a command's job ends with one)
        return result

    async def read_now(self, sensor: str) -> None:
        await self._job(functools.partial(self.master.read_now, sensor))

    async def passthrough(self, sensor: str, pdu: bytes) -> bytes:
        answer = await self._job(functools.partial(self.master.passthrough, sensor, pdu))
        assert isinstance(answer, bytes)  # (a pass-through's ends with the answer PDU)
        return answer

    def record_frames(self, size: int) -> None:
        """Keep the line's last ``size`` frames (event capture; before ``start``)."""
        config, master = self.master.config, self.master
        master.link = RecordingLink(config.port, config.baudrate, rs485=config.rs485,
                                    size=size,
                                    asked=lambda: master.schedule.line.attempt is not None)

    async def frames(self) -> list[Frame]:
        """The line's recent frames (event capture), copied on the bus thread; none
        when they are not kept or the bus is not running."""
        link = self.master.link
        if not isinstance(link, RecordingLink) or not self.reactor.running:
            return []
        return await self.call(link.copy)

    async def watch(self, watcher: Callable[[Trace], None]) -> Callable[[], None]:
        """Tell ``watcher`` (on the cache's loop, in order) every exchange of the line
        from now on; returns what stops it.  The bus makes Trace events only while
        someone watches (or its log traces)."""
        def on_bus_thread(event: Trace) -> None:
            self.writer.hand_urgent(watcher, event)

        await self.call(functools.partial(self.master.watch, on_bus_thread))

        def unwatch() -> None:
            self.reactor.post(functools.partial(self.master.watch, on_bus_thread, False))

        return unwatch

    async def pause(self, reason: str) -> float:
        """Release the line's port (``PortKeeper.pause``); when the line is quiet, on
        ``time.monotonic()``'s clock (the loop's)."""
        return await self.call(functools.partial(self.master.port.pause, reason))

    async def resume(self) -> None:
        await self.call(functools.partial(self.master.port.pause, None))

    async def change_sensors(self, config: BusConfig, grace: float) -> None:
        """(A reload) The bus's sensors are ``config``'s from now on
        (``BusMaster.change_sensors``): returns once the gone ones have left (or after
        ``grace``), and what the bus handed the cache by then has reached it."""
        if not self.reactor.running:  # (nothing else touches the master)
            self.master.change_sensors(config, lambda: None)
            return
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()

        def done() -> None:  # (on the bus thread: after the writes before it)
            self.writer.hand_urgent(_settle_none, future)

        await self.call(functools.partial(self.master.change_sensors, config, done))
        try:
            await asyncio.wait_for(asyncio.shield(future), grace)
        except TimeoutError:
            log.warning("bus %s: a removed sensor's exchange not over after %.0f s; "
                        "going on", self.master.name, grace)

    def stop(self) -> None:
        """Ask the master to finish its exchange in flight and stop."""
        self.reactor.post(self.master.stop)


class BusThread:
    """The bus thread and its runners."""

    def __init__(self, buses: list[BusConfig], cache: Cache) -> None:
        self.reactor = Reactor("bus")
        self.writer = CacheWriter(cache)  # one for every line: one hand-over per turn
        self.reactor.after_each_turn(self.writer.flush, self.writer.next_at)
        self.runners = {bus.name: BusRunner(bus, self.writer, self.reactor)
                        for bus in buses}

    def start(self) -> None:
        """Start the bus thread; the cache's loop is the running one."""
        self.writer.loop = asyncio.get_running_loop()
        for runner in self.runners.values():
            runner.start()
        if self.runners:
            self.reactor.start()

    async def stop(self, grace: float) -> None:
        """Stop every bus after its exchange in flight; past ``grace``, at once."""
        for runner in self.runners.values():
            runner.stop()
        if not await asyncio.to_thread(self.reactor.join, grace):
            log.warning("buses not stopped after %.0f s; stopping them now", grace)
            for runner in self.runners.values():
                self.reactor.post(runner.master.finish)
            if not await asyncio.to_thread(self.reactor.join, 5.0):
                return  # (its pipe stays open: the thread may still post to it)
        self.reactor.close()
        # The masters' last counters and states: nobody may read the cache again to
        # take them, and a lazy hand-over's timer would not run before the loop ends.
        self.writer.cache.catch_up()

    # ------------------------------------------------------------ a reload

    async def stop_one(self, name: str, grace: float) -> None:
        """Stop one bus (its exchange in flight finished, its port closed) while the
        others run on; its runner is dropped.  The thread is held meanwhile: a loop
        whose every client is done would end (``Reactor._main``)."""
        runner = self.runners.pop(name)
        if not self.reactor.running:
            return
        hold = _Hold()
        self.reactor.post(functools.partial(self.reactor.clients.append, hold))
        runner.stop()
        try:
            deadline = asyncio.get_running_loop().time() + grace
            while not await runner.call(lambda: runner.master.done):
                if asyncio.get_running_loop().time() > deadline:
                    log.warning("bus %s: not stopped after %.0f s; stopping it now", name, grace)
                    self.reactor.post(runner.master.finish)
                    break
                await asyncio.sleep(0.01)
        finally:
            self.reactor.post(functools.partial(_drop, self.reactor, runner.master))
            self.reactor.post(functools.partial(_drop, self.reactor, hold))
        await self._handed_over()

    async def _handed_over(self) -> None:
        """Wait until what the bus thread handed the cache so far has reached it (a
        stopped master's last counters must not arrive after its bus is gone)."""
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        marker = functools.partial(_settle_none, future)
        if self.reactor.post(functools.partial(self.writer.hand_urgent, marker)):
            await future

    def start_one(self, config: BusConfig, frames: int | None = None) -> BusRunner:
        """A new bus on the running thread (``frames``: its frames kept, as
        ``record_frames``)."""
        runner = BusRunner(config, self.writer, self.reactor)
        if frames is not None:
            runner.record_frames(frames)
        self.runners[config.name] = runner
        if self.reactor.running:
            runner.start()
        return runner


def _settle_none(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


class _Hold:
    """A client of the bus loop that keeps it running while a bus is replaced."""

    done = False

    def next_at(self) -> float:
        return math.inf

    def on_timer(self, now: float) -> None:
        pass


def _drop(reactor: Reactor, client: object) -> None:
    """(On the bus thread.)"""
    with contextlib.suppress(ValueError):
        reactor.clients.remove(client)  # type: ignore[arg-type]
