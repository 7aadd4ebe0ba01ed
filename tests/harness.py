"""Running a Gateway inside a test: shared by the bus master and front-end tests."""

from __future__ import annotations

import asyncio
import contextlib
import inspect
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

from gateway.app import Gateway
from gateway.config import config_from_dict


@contextlib.asynccontextmanager
async def running(config: dict[str, Any]) -> AsyncIterator[Gateway]:
    """A gateway on ``config`` (a dict as the YAML would give), running until the block
    ends; its front ends are listening when the block starts."""
    gateway = Gateway(config_from_dict(config, env={}))
    stop = asyncio.Event()
    task = asyncio.create_task(gateway.run(stop))
    try:
        await until(lambda: task.done() or gateway.modbus is None or gateway.modbus.listening)
        if task.done():
            task.result()  # it could not start: raise why
        yield gateway
    finally:
        stop.set()
        await asyncio.wait_for(task, 15)


async def until(condition: Callable[[], bool | Awaitable[bool]], timeout: float = 10.0) -> None:
    """Wait for a condition of the system under test (a deadline, not a measurement).

    The deadline is checked between polls rather than by cancelling them: Python
    3.11's ``wait_for`` can lose a cancellation that races with the inner
    ``wait_for`` of a pymodbus request, and the wait would then never end."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        value = condition()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return
        if loop.time() > deadline:
            raise TimeoutError(f"condition not met within {timeout} s")
        await asyncio.sleep(0.01)


def run(coro: Callable[[], Awaitable[None]]) -> None:
    """Run an async test body on a fresh event loop."""
    async def main() -> None:
        await coro()

    asyncio.run(main())
