"""A bus master on a thread of its own.

The line's timing must not depend on what the front ends are doing: with a hundred
Modbus TCP clients on the main event loop, each turn of that loop runs a long burst of
their callbacks, and a bus master sharing the loop would send each next request that
much later (measured: the bus rate fell by a third, ``docs/benchmarks.md``).  So each
bus master runs its own event loop on its own thread.

The master writes to the cache through ``CacheWriter``, which hands every write to the
loop that owns the cache, in order, so cache listeners (the front ends) always run
there.  Its counters travel the same way, as frozen snapshots made on the bus thread
(``BusMaster.stats_snapshot``): the front ends never touch the master's state.
Calls into the master (commands, on-demand reads, pass-through) go through
``BusRunner.call``.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import selectors
import threading
from collections.abc import Awaitable, Callable, Coroutine, Mapping
from typing import Any, TypeVar

from ..cache import Cache
from ..config import BusConfig
from ..errors import ErrorKind, RequestFailed
from ..model import Reading
from ..stats import BusStats, SensorStats
from ..threads import tighten_timers
from .link import BUS_NICE
from .master import BusMaster

log = logging.getLogger("imu_gateway.bus")
T = TypeVar("T")


def _precise_loop() -> asyncio.AbstractEventLoop:
    return asyncio.SelectorEventLoop(selectors.SelectSelector())


class CacheWriter:
    """The cache's write side, used from a bus thread."""

    def __init__(self, cache: Cache, runner: BusRunner) -> None:
        self.cache = cache
        self.runner = runner
        self.loop: asyncio.AbstractEventLoop | None = None  # the cache's loop, set at start

    def _hand_over(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        assert self.loop is not None
        self.loop.call_soon_threadsafe(functools.partial(fn, *args, **kwargs))

    def publish(self, name: str, reading: Reading, at: float | None = None) -> None:
        self._hand_over(self.cache.publish, name, reading, at)

    def set_state(self, name: str, *, online: bool | None = None, busy: bool | None = None,
                  streaming: bool | None = None) -> None:
        self._hand_over(self.cache.set_state, name, online=online, busy=busy,
                        streaming=streaming)

    def count_error(self, name: str) -> None:
        self._hand_over(self.cache.count_error, name)

    def note_stats(self, bus: BusStats, sensors: Mapping[str, SensorStats]) -> None:
        self._hand_over(self.cache.note_stats, bus, sensors)


class BusRunner:
    def __init__(self, config: BusConfig, cache: Cache) -> None:
        self.writer = CacheWriter(cache, self)
        self.master = BusMaster(config, self.writer)
        # the counters as they are before the thread runs (read here, while no other
        # thread touches them): the front ends never see a bus without any
        cache.note_stats(*self.master.stats_snapshot())
        self._thread = threading.Thread(target=self._main, name=f"bus {config.name}",
                                        daemon=True)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._ready = threading.Event()

    def start(self) -> None:
        """Start the thread; the cache's loop is the running one."""
        self.writer.loop = asyncio.get_running_loop()
        self._thread.start()
        self._ready.wait()

    def _main(self) -> None:
        async def run() -> None:
            self._loop = asyncio.get_running_loop()
            self._task = asyncio.current_task()
            self._ready.set()
            await self.master.run()

        tighten_timers(BUS_NICE)
        try:
            # select() rather than epoll: epoll's timeouts are whole milliseconds, and
            # the waits here (a Modbus silent interval is 1.75 ms) are not.  The loop
            # watches one descriptor, its own wake-up pipe (bytes come from the link's
            # reader thread).
            with asyncio.Runner(loop_factory=_precise_loop) as runner:
                runner.run(run())
        except asyncio.CancelledError:
            pass
        except Exception:
            log.exception("bus %s: the bus master failed", self.master.name)

    def call(self, coro: Coroutine[Any, Any, T]) -> Awaitable[T]:
        """Run ``coro`` on the bus's loop; await the result on the caller's.  Raises
        ``RequestFailed`` when the bus is not running (not started, or stopped)."""
        loop = self._loop
        try:
            if loop is None or loop.is_closed():
                raise RuntimeError("not running")
            return asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, loop))
        except RuntimeError:  # the loop closed under us: the bus has stopped
            coro.close()
            raise RequestFailed(ErrorKind.OFFLINE,
                                f"bus {self.master.name} is not running") from None

    def stop(self) -> None:
        """Ask the master to finish its exchange in flight and stop."""
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self.master.stop)

    async def join(self, timeout: float) -> None:
        """Wait for the thread; past ``timeout`` the master is cancelled."""
        if self._thread.ident is None:
            return  # never started
        await asyncio.to_thread(self._thread.join, timeout)
        if self._thread.is_alive() and self._loop is not None and self._task is not None:
            log.warning("bus %s: not stopped after %.0f s; cancelling", self.master.name, timeout)
            self._loop.call_soon_threadsafe(self._task.cancel)
            await asyncio.to_thread(self._thread.join, 5.0)
