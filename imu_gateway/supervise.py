"""Front ends that fail alone, and warnings about peers that cannot flood the log.

A front end (Modbus TCP, MQTT, HTTP) serves peers the gateway does not control.  If
one of its parts fails (a cache listener, a task of its own, a callback from a
library's thread), that front end is stopped and started again with back-off; the
buses and the other front ends go on.  Only a signal, or a fatal error at start-up,
ends the process (docs/reliability.md).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger("imu_gateway")

RESTART_MIN, RESTART_MAX = 1.0, 60.0  # seconds between a failure and the restart
#: a front end that ran this long since its last restart starts the back-off anew
RESTART_RESET_S = 300.0


class Frontend:
    """What the supervisor needs of a front end: ``start``, ``stop`` and ``fail``.

    A front end reports a failure of any of its parts with ``fail(exc)``: the first
    since the last start wakes the supervisor, later ones are the same failure."""

    name = "frontend"

    def __init__(self) -> None:
        self._failure: asyncio.Future[BaseException] | None = None

    async def start(self) -> None:
        raise NotImplementedError

    async def stop(self) -> None:
        raise NotImplementedError

    def arm(self) -> None:
        """A new life: the next ``fail`` wakes the supervisor again."""
        self._failure = asyncio.get_running_loop().create_future()

    def fail(self, exc: BaseException) -> None:
        if self._failure is not None and not self._failure.done():
            self._failure.set_result(exc)
        else:  # before the supervisor runs, or during a restart already under way
            log.debug("%s: a further failure: %r", self.name, exc)

    def guarded(self, task: asyncio.Task[None]) -> None:
        """A task of this front end: when it ends with an exception, the front end failed."""
        def done(task: asyncio.Task[None]) -> None:
            if not task.cancelled() and task.exception() is not None:
                self.fail(task.exception())  # type: ignore[arg-type]
        task.add_done_callback(done)

    async def failed(self) -> BaseException:
        assert self._failure is not None, "arm() first"
        return await self._failure


@dataclass
class Supervisor:
    """Restarts failed front ends; ``restarts`` counts them by name."""

    restarts: Counter[str] = field(default_factory=Counter)

    async def watch(self, frontend: Frontend) -> None:
        """Run until cancelled: wait for ``frontend`` to fail, then restart it."""
        delay = RESTART_MIN
        started = time.monotonic()
        while True:
            exc = await frontend.failed()
            self.restarts[frontend.name] += 1
            if time.monotonic() - started > RESTART_RESET_S:
                delay = RESTART_MIN
            log.error("%s failed (%s); restarting it in %g s; the rest goes on",
                      frontend.name, _describe(exc), delay)
            log.debug("%s: the failure", frontend.name, exc_info=exc)
            with contextlib.suppress(Exception):  # a broken front end may not stop cleanly
                await frontend.stop()
            await asyncio.sleep(delay)
            delay = min(delay * 2, RESTART_MAX)
            frontend.arm()
            started = time.monotonic()
            try:
                await frontend.start()
            except Exception as error:  # tried again after the back-off
                frontend.fail(error)


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class RepeatFilter(logging.Filter):
    """For a library's logger that warns once per request (uvicorn, for each request
    with an ``Upgrade`` header): each message lets one record through a period; the
    rest are counted, and the count is said on the next one let through."""

    def __init__(self, period: float = 60.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.period = period
        self._clock = clock
        self._since: dict[str, float] = {}
        self._held: Counter[str] = Counter()

    def filter(self, record: logging.LogRecord) -> bool:
        key, now = str(record.msg), self._clock()
        if now - self._since.get(key, -math.inf) < self.period:
            self._held[key] += 1
            return False
        self._since[key] = now
        if held := self._held.pop(key, 0):
            record.msg = f"{record.msg} (and {held} more like it in the last {self.period:g} s)"
        return True


class PeerLog:
    """Warnings about peers, at most one line per kind a period: the first is logged
    at once, the rest are counted and summed up in one line when the period ends.
    A client that connects a thousand times, or a fuzzer, then costs the log two
    lines a minute, not a thousand."""

    def __init__(self, logger: logging.Logger, period: float = 60.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._log = logger
        self.period = period
        self._clock = clock
        self._since: dict[str, float] = {}  # kind -> when its period began
        self._held: Counter[str] = Counter()  # kind -> warnings not logged this period

    def warning(self, kind: str, message: str, *args: object) -> None:
        now = self._clock()
        began = self._since.get(kind)
        if began is not None and now - began < self.period:
            self._held[kind] += 1
            return
        self.flush(kind)
        self._since[kind] = now
        self._log.warning(message, *args)

    def flush_due(self) -> None:
        """Log the counts of the periods that ended (the owner calls it now and then)."""
        now = self._clock()
        for kind in [k for k in self._held if now - self._since[k] >= self.period]:
            self.flush(kind)
            self._since.pop(kind, None)

    def flush(self, kind: str | None = None) -> None:
        """Log the counts held back (of ``kind``, or of every kind)."""
        for key in [kind] if kind is not None else list(self._held):
            held = self._held.pop(key, 0)
            if held:
                self._log.warning("... and %d more %s in the last %g s", held, key,
                                  self.period)
