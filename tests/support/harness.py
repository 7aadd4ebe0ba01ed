"""Running a Gateway inside a test: shared by the bus master and front-end tests."""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import signal
import socket
import subprocess
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

from imu_gateway.app import Gateway
from imu_gateway.config import config_from_dict, load_config
from imu_gateway.config.loading import ConfigSource
from imu_gateway.model import WireProtocol
from imu_gateway.normalise import field_values
from imu_gateway.simulator import SimSensor

# The reading JSON's per-field names in order, written out here so the tests do not trust
# the gateway's.
FIELDS = ("pitch", "roll", "yaw", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y",
          "gyro_z", "mag_x", "mag_y", "mag_z", "q0", "q1", "q2", "q3")
GROUP_OF = {**dict.fromkeys(FIELDS[0:3], "angles"), **dict.fromkeys(FIELDS[3:6], "accel"),
            **dict.fromkeys(FIELDS[6:9], "gyro"), **dict.fromkeys(FIELDS[9:12], "mag"),
            **dict.fromkeys(FIELDS[12:16], "quaternion")}
#: Half the native protocol's BCD resolution per group (SXXX.YY, S.YYYY, …).
NATIVE_STEP = {"angles": 0.005, "accel": 0.00005, "gyro": 0.005, "mag": 0.000005,
               "quaternion": 0.0000005}


def fields_of(reading_json: dict[str, Any]) -> dict[str, float]:
    """The reading JSON's values (docs/mqtt.md) by its per-field names."""
    out = {}
    for name in FIELDS:
        group = reading_json.get(GROUP_OF[name])
        if group is not None:
            member = name.split("_")[1] if GROUP_OF[name] in ("accel", "gyro", "mag") else name
            out[name] = group[member]
    return out


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def expected(sim: SimSensor) -> dict[str, float]:
    """What the simulated sensor reports (its held reading through its settings)."""
    return field_values(sim.measure(0.0))


def tolerance(protocol: WireProtocol, name: str, value: float) -> float:
    """The sensor's resolution: BCD steps (native) or float32 (Modbus RTU)."""
    if protocol is WireProtocol.NATIVE:
        return NATIVE_STEP[GROUP_OF[name]] + 1e-6 * abs(value)
    return 1e-6 * max(1.0, abs(value))


@contextlib.asynccontextmanager
async def running(config: dict[str, Any] | Path,
                  env: dict[str, str] | None = None) -> AsyncIterator[Gateway]:
    """A gateway on ``config`` (a dict as the YAML would give, ``${VAR}`` taken from
    ``env``; or a config file, which a reload then saves to), running until the block
    ends; its front ends are listening when the block starts."""
    if isinstance(config, Path):
        gateway = Gateway(load_config(config), ConfigSource.read(config))
    else:
        gateway = Gateway(config_from_dict(config, env=env or {}))
    stop = asyncio.Event()
    task = asyncio.create_task(gateway.run(stop))
    try:
        servers = [s for s in (gateway.modbus, gateway.http, gateway.opcua) if s is not None]
        await until(lambda: task.done() or all(s.listening for s in servers))
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


def interrupt(process: subprocess.Popen[Any], timeout: float = 15.0) -> int:
    """Stop a process a test started the way a user would (SIGINT), kill it if it does
    not stop within ``timeout``, and reap it whatever happened: no process outlives its
    test.  Its exit status (negative: the signal that ended it)."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
    return process.wait()
