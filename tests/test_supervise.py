"""The supervisor's restart rule and the rate-limited peer warnings, on their own."""

from __future__ import annotations

import asyncio
import logging

import pytest
from support.harness import until

from imu_gateway import supervise
from imu_gateway.supervise import Frontend, PeerLog, RepeatFilter, Supervisor


class Flaky(Frontend):
    name = "flaky"

    def __init__(self, failing_starts: int) -> None:
        super().__init__()
        self.starts = self.stops = 0
        self.failing_starts = failing_starts

    async def start(self) -> None:
        self.starts += 1
        if self.starts <= self.failing_starts:
            raise OSError("address in use")

    async def stop(self) -> None:
        self.stops += 1
        raise RuntimeError("a broken front end may not stop cleanly either")


@pytest.mark.anyio
async def test_a_failed_frontend_is_restarted_with_back_off(monkeypatch: pytest.MonkeyPatch,
                                                      caplog: pytest.LogCaptureFixture) -> None:
    delays: list[float] = []
    real_sleep = asyncio.sleep

    async def sleep(delay: float) -> None:
        delays.append(delay)
        await real_sleep(0)

    monkeypatch.setattr(asyncio, "sleep", sleep)

    frontend = Flaky(failing_starts=3)  # the first restarts fail to start again
    frontend.arm()
    supervisor = Supervisor()
    watcher = asyncio.create_task(supervisor.watch(frontend))
    frontend.fail(ValueError("a peer's bad value"))
    frontend.fail(ValueError("the same failure, again"))  # not a second restart
    await until(lambda: frontend.starts == 4)
    assert supervisor.restarts["flaky"] == 4  # the failure, then three failed starts
    # (``until`` polls with short sleeps of its own)
    assert [d for d in delays if d >= supervise.RESTART_MIN] == [1.0, 2.0, 4.0, 8.0]
    frontend.fail(KeyError("later"))  # still watched after a good start
    await until(lambda: supervisor.restarts["flaky"] == 5)
    watcher.cancel()
    await asyncio.gather(watcher, return_exceptions=True)

    messages = [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR]
    assert messages[0] == ("flaky failed (ValueError: a peer's bad value); restarting it "
                           "in 1 s; the rest goes on")
    assert "OSError: address in use" in messages[1]


def test_peer_warnings_are_one_line_then_a_count(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    peers = PeerLog(logging.getLogger("test.peers"), period=60, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, "test.peers"):
        for i in range(1000):
            peers.warning("refused", "refused client %d", i)
            now[0] += 0.01  # 10 s in all
        peers.warning("bad_mbap", "bad header")
        peers.flush_due()  # the period has not ended
        now[0] = 61.0
        peers.flush_due()
        peers.warning("refused", "refused client %d", 1000)
    assert [r.getMessage() for r in caplog.records] == [
        "refused client 0", "bad header", "... and 999 more refused in the last 60 s",
        "refused client 1000"]


def test_a_library_warning_per_request_is_let_through_once_a_period(
        caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    logger = logging.getLogger("test.library")
    limiter = RepeatFilter(period=60, clock=lambda: now[0])
    logger.addFilter(limiter)
    try:
        with caplog.at_level(logging.WARNING, "test.library"):
            for _ in range(500):
                logger.warning("Unsupported upgrade request.")
            logger.warning("another message")
            now[0] = 60.0
            logger.warning("Unsupported upgrade request.")
    finally:
        logger.removeFilter(limiter)
    assert [r.getMessage() for r in caplog.records] == [
        "Unsupported upgrade request.", "another message",
        "Unsupported upgrade request. (and 499 more like it in the last 60 s)"]
