"""The bus thread's plumbing, step by step, without a serial line: the loop's wake-up
pipe (``Reactor``) and the hand-over of the cache writes to the main loop
(``CacheWriter``).  Each race is played in one thread, in the order that hurt."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import select
import time
from collections.abc import Callable
from typing import Any

import pytest

from imu_gateway.bus.link import SerialLink
from imu_gateway.bus.reactor import Reactor
from imu_gateway.bus.runner import CacheWriter
from imu_gateway.cache import Cache
from imu_gateway.errors import LinkError


def _pipe_has_bytes(r: Reactor) -> bool:
    return bool(select.select([r._wake_r], [], [], 0)[0])


def test_a_post_while_the_wakeup_pipe_is_read_still_wakes_the_next_time(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Another thread posts while the loop empties the pipe.  Afterwards the flag must
    not say "a byte is in the pipe" when none is: else no later post writes one, and
    the loop would wake for timers only."""
    r = Reactor()
    ran: list[str] = []
    r.post(lambda: ran.append("first"))
    real_read = os.read
    posted = False

    def read_with_a_post_between(fd: int, n: int) -> bytes:
        nonlocal posted
        if not posted:
            posted = True
            r.post(lambda: ran.append("second"))  # the other thread, in the window
        return real_read(fd, n)

    monkeypatch.setattr(os, "read", read_with_a_post_between)
    r._drain_wakeups()
    monkeypatch.setattr(os, "read", real_read)
    assert not r._woken or _pipe_has_bytes(r)
    while r._posted:  # what the same turn of the loop does next
        r._posted.popleft()()
    assert ran == ["first", "second"]
    r.post(lambda: ran.append("third"))  # a later post wakes the loop
    assert _pipe_has_bytes(r)
    r.close()


@pytest.mark.anyio
async def test_cache_writes_reach_the_main_loop_in_order_and_it_is_not_held() -> None:
    """With a prompt listener: turns handed over while the main loop has not run the
    last hand-over join it (one wake-up); a hand-over runs only the turns there when it
    started, so a bus that keeps handing over cannot keep the main loop from its other
    work."""
    loop = asyncio.get_running_loop()
    cache = Cache([])
    cache.subscribe(lambda kind, snap: None)  # (prompt: every turn at once)
    writer = CacheWriter(cache)
    writer.loop = loop
    seen: list[int] = []
    woken = 0
    real = loop.call_soon_threadsafe

    def counted(fn: Callable[..., Any], *args: Any) -> asyncio.Handle:
        nonlocal woken
        woken += 1
        return real(fn, *args)

    loop.call_soon_threadsafe = counted  # type: ignore[method-assign,assignment]
    try:
        for turn in range(3):
            writer.hand(seen.append, turn)
            writer.flush()
        assert woken == 1  # the later turns joined the first hand-over
        other_work = asyncio.Event()
        loop.call_soon(other_work.set)

        def a_busy_bus(turn: int) -> None:
            seen.append(turn)
            if turn < 1000:  # a turn that hands over the next one while it runs
                writer.hand(a_busy_bus, turn + 1)
                writer.flush()

        writer.hand(a_busy_bus, 3)
        writer.flush()
        await asyncio.wait_for(other_work.wait(), 5)
        assert len(seen) < 1000  # the main loop got to its other work in between
        while len(seen) < 1001:
            await asyncio.sleep(0)
        assert seen == list(range(1001))
    finally:
        loop.call_soon_threadsafe = real  # type: ignore[method-assign]


def test_a_port_that_takes_no_more_output_is_lost_at_once() -> None:
    """The bus thread carries every line: a port whose output is stuck (flow control
    held, a hung adapter) must be given up on, not waited on or spun on."""
    read_end, write_end = os.pipe()  # a descriptor that stops taking bytes, as a tty does
    os.set_blocking(write_end, False)
    try:
        with contextlib.suppress(BlockingIOError):
            while True:
                os.write(write_end, b"\0" * 65536)
        link = SerialLink("/dev/ttyUSB7", 115200)
        with pytest.raises(LinkError, match=r"/dev/ttyUSB7 takes no more output \(0 of 8"):
            link._write_now(write_end, bytes(8), math.inf)
        os.read(read_end, 65536)  # room again: a request goes out whole
        assert link._write_now(write_end, bytes(8), math.inf)
        assert os.read(read_end, 65536) == bytes(8)
        # past the latest time it was given (a thread held before the write): not sent
        assert not link._write_now(write_end, bytes(8), time.monotonic() - 0.001)
        os.set_blocking(read_end, False)
        with pytest.raises(BlockingIOError):
            os.read(read_end, 65536)
    finally:
        os.close(read_end)
        os.close(write_end)


def test_a_post_after_the_close_writes_to_no_descriptor() -> None:
    """A port's helper thread may post after the bus thread ended and closed its pipe:
    the post must not write into whatever file now has that descriptor number."""
    r = Reactor()
    r.close()
    read_end, write_end = os.pipe()  # the lowest free numbers: likely the old pipe's
    try:
        r.post(lambda: None)
        assert not select.select([read_end], [], [], 0)[0]
    finally:
        os.close(read_end)
        os.close(write_end)


def test_after_the_loop_ended_a_post_is_refused_and_a_call_fails() -> None:
    """Whoever waits for work posted to an ended loop is told at once; nothing is
    taken that would never run."""
    r = Reactor()
    r.start()
    ran = r.call(lambda: "ran")
    assert ran.result(5) == "ran"
    r.end()
    assert r.join(5)
    assert r.post(lambda: None) is False
    late = r.call(lambda: "never")
    with pytest.raises(RuntimeError, match="the bus thread has ended"):
        late.result(5)
    r.close()
