"""The bus thread: one ``select()`` loop that carries every serial line of the process.

Why not asyncio here: measured on the 2-core VM (``docs/benchmarks.md``), an asyncio
loop costs about twice the CPU of a bare ``select()`` loop per wake-up, and a line at
115200 baud wakes its owner two or three times per exchange.  With a thread and a loop
per line the gateway spent 0.7-0.9 ms of CPU per exchange; a bare loop polling the same
sensor spends 0.13.  This loop does only what a bus needs: watch descriptors, keep one
timer per client, and run calls posted from other threads.

Each client (a bus master) stays the one owner of its line: the loop only asks it when
it next needs a turn (``next_at``) and gives it one (``on_timer``); its descriptors'
callbacks are its own.  A client's exception is logged and costs that client's turn,
not the other lines.

Waits are ``select()``'s, which keeps sub-millisecond timeouts (epoll's are whole
milliseconds, and a Modbus silent interval at 19200 baud is 1.75 ms).  ``select()``
watches descriptors below ``FD_SETSIZE`` only: a port opened past it is read by a
thread of its own (``link``).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import select
import threading
import time
import typing
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, TypeVar

from ..threads import tighten_timers

log = logging.getLogger("imu_gateway.bus")
T = TypeVar("T")

#: The thread's niceness, where the system allows it: a line's timing is the machine's
#: to keep even when other work takes the CPU (the systemd unit can grant CAP_SYS_NICE).
BUS_NICE = -10
#: ``select()`` watches descriptors below this only.
FD_SETSIZE = 1024
#: The longest wait with nothing due: a bound, so a lost wake-up costs this at most.
IDLE_WAIT = 0.5


class Client(typing.Protocol):
    """What the loop asks of a bus master."""

    def next_at(self) -> float:
        """When it next needs a turn (``math.inf``: only when woken)."""

    def on_timer(self, now: float) -> None: ...

    @property
    def done(self) -> bool:
        """It has stopped for good: the loop ends when every client has."""


class Reactor:
    """The loop.  ``post`` and ``call`` may be used from any thread; everything else
    from the loop's own thread only."""

    def __init__(self, name: str = "bus") -> None:
        self.clients: list[Client] = []
        self._readers: dict[int, Callable[[], None]] = {}
        self._posted: deque[Callable[[], None]] = deque()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._woken = False  # a wake-up byte is in the pipe and not read yet
        self._closing = threading.Lock()  # a post and the loop's end: one at a time
        self._finished = False  # the loop ran its last posts: no more are taken
        self._thread = threading.Thread(target=self._main, name=name, daemon=True)
        self._after: list[Callable[[], None]] = []  # run at the end of each turn of the loop
        self._deadlines: list[Callable[[], float]] = []  # (theirs: a turn by then)
        self.running = False
        self._ended = False

    # ------------------------------------------------------------ any thread

    def start(self) -> None:
        self.running = True
        self._thread.start()

    def post(self, fn: Callable[[], None]) -> bool:
        """Run ``fn`` on the loop's thread, soon, in the order posted.  False: the loop
        has ended and ``fn`` will never run (whoever waits for it must be told)."""
        with self._closing:  # (a post and the loop's last drain: one at a time)
            if self._finished:
                return False
            self._posted.append(fn)
            if not self._woken:
                self._woken = True
                with contextlib.suppress(BlockingIOError):  # full of wake-ups already
                    os.write(self._wake_w, b"\0")
        return True

    def call(self, fn: Callable[[], T]) -> Future[T]:
        """``fn()`` on the loop's thread; its result (or exception) in the future."""
        future: Future[T] = Future()

        def run() -> None:
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn())
                except BaseException as exc:  # handed to the caller, not raised here
                    future.set_exception(exc)

        if not self.post(run):
            future.set_exception(RuntimeError("the bus thread has ended"))
        return future

    def end(self) -> None:
        """End the loop whatever its clients are doing (a loop without any ends only
        so)."""
        self.post(functools.partial(setattr, self, "_ended", True))

    def join(self, timeout: float) -> bool:
        """Wait for the thread; True when it has ended (or never started)."""
        if self._thread.ident is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    # ------------------------------------------------------------ the loop's thread

    def watch(self, fd: int, callback: Callable[[], None]) -> None:
        self._readers[fd] = callback

    def unwatch(self, fd: int) -> None:
        self._readers.pop(fd, None)

    def after_each_turn(self, fn: Callable[[], None],
                        next_at: Callable[[], float] | None = None) -> None:
        """Run ``fn`` at the end of every turn of the loop (the cache writer's flush:
        one hand-over to the main loop per turn, whatever the turn did), and a turn at
        ``next_at()`` at the latest (its lazy hand-over's time)."""
        self._after.append(fn)
        if next_at is not None:
            self._deadlines.append(next_at)

    def _main(self) -> None:
        tighten_timers(BUS_NICE)
        while not self._ended and not (self.clients and all(c.done for c in self.clients)):
            try:
                self._once()
            except Exception:  # a bug here must not end every line: logged, go on
                log.exception("bus thread: internal error in its loop")
                time.sleep(0.1)
        self.running = False
        while True:  # asked before the end: answered (a stopped bus refuses)
            while self._posted:
                self._guarded(self._posted.popleft())
            with self._closing:
                if not self._posted:
                    self._finished = True  # later posts are refused, not lost
                    break
        for fn in self._after:
            self._guarded(fn)

    def close(self) -> None:
        """After the thread has ended: its wake-up pipe.  (Threads that open ports or
        read them may still post: their posts are dropped, never written to a closed
        descriptor, whose number the process may have given to another file.)"""
        with self._closing:
            self._finished = True
            for fd in (self._wake_r, self._wake_w):
                with contextlib.suppress(OSError):
                    os.close(fd)

    def _once(self) -> None:
        now = time.monotonic()
        wake = min((c.next_at() for c in self.clients), default=now + IDLE_WAIT)
        for deadline in self._deadlines:
            wake = min(wake, deadline())
        timeout = min(max(wake - now, 0.0), IDLE_WAIT)
        if self._posted:
            timeout = 0.0
        try:
            ready, _, _ = select.select([self._wake_r, *self._readers], [], [], timeout)
        except OSError:  # a descriptor closed under its reader: drop it, go on
            self._drop_closed()
            return
        for fd in ready:
            if fd == self._wake_r:
                self._drain_wakeups()
            elif (callback := self._readers.get(fd)) is not None:
                self._guarded(callback)
        while self._posted:
            self._guarded(self._posted.popleft())
        now = time.monotonic()
        for client in self.clients:
            if client.next_at() <= now:
                self._guarded(lambda c=client: c.on_timer(now))  # type: ignore[misc]
        for fn in self._after:
            self._guarded(fn)

    def _drop_closed(self) -> None:
        for fd in list(self._readers):
            try:
                os.fstat(fd)
            except OSError:
                log.error("bus thread: descriptor %d was closed while watched", fd)
                self._readers.pop(fd)

    def _drain_wakeups(self) -> None:
        with contextlib.suppress(BlockingIOError):
            while os.read(self._wake_r, 4096):
                pass
        # After the pipe is empty, not before: a post in between would write a byte the
        # read swallows, leave the flag set on an empty pipe, and no later post would
        # wake the loop again.  A post that sees the flag still set is in ``_posted``,
        # which this turn runs next.
        self._woken = False

    @staticmethod
    def _guarded(fn: Callable[[], Any]) -> None:
        try:
            fn()
        except Exception:
            log.exception("bus thread: internal error (the other lines go on)")
