"""What the benchmarks share: free ports, and the simulator and the gateway as
processes of their own (as in a plant, they share no interpreter with the load)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import multiprocessing
import resource
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

from imu_gateway.app import Gateway
from imu_gateway.config import GatewayConfig, config_from_dict
from imu_gateway.model import Reading
from imu_gateway.simulator.motion import Motion


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def processes(sensor_yaml: str, interfaces_yaml: str, *others: list[str],
              baud: int = 115200) -> Iterator[None]:
    """A simulated native AH on a pty, ``imu-gateway run`` with one bus of that
    sensor (``sensor_yaml``: its YAML mapping, ``{name: boom, series: AH, …}``) and the
    interfaces of ``interfaces_yaml``, and ``others`` (further commands), until the
    block ends."""
    python = sys.executable
    simulator = subprocess.Popen(
        [python, "-m", "imu_gateway", "simulate", "--protocol", "native", "--series", "AH",
         "--baud", str(baud)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert simulator.stdout is not None
    pty = simulator.stdout.readline().split()[1]
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "bench.yaml"
        config.write_text(f"""
buses:
  - name: bench
    port: {pty}
    baudrate: {baud}
    protocol: native
    sensors: [{sensor_yaml}]
{interfaces_yaml}
""")
        procs = [subprocess.Popen([python, "-m", "imu_gateway", "run", "-c", str(config),
                                   "--log-level", "warning"]),
                 *(subprocess.Popen(cmd, stderr=subprocess.DEVNULL) for cmd in others)]
        try:
            yield
        finally:
            running: list[subprocess.Popen[bytes] | subprocess.Popen[str]] = [*procs, simulator]
            for proc in running:
                proc.terminate()
                proc.wait(10)


#: The fed benchmarks' sensors: AH sensors on a line that does not open, whose readings
#: the benchmark puts into the cache itself (``fed``), at the rate it chooses.
FED_SENSORS = 4


def fed_config(**front_ends: object) -> GatewayConfig:
    return config_from_dict({
        "gateway_id": "bench",
        "buses": [{"name": "a", "port": "/dev/null-bench", "baudrate": 115200,
                   "protocol": "native",
                   "sensors": [{"name": f"s{i}", "series": "AH", "address": i,
                                "poll_hz": 1} for i in range(FED_SENSORS)]}],
        **front_ends}, env={})


class Fed(NamedTuple):
    """What a fed run measured."""

    delivered: int  # what the counter put in its queue
    cores: float  # the gateway's CPU: process time ÷ wall time
    system: float  # of which in the kernel (system calls: sockets, epoll, the loopback)
    wakeups: float  # the gateway's threads' sleeps a second (voluntary context switches)


async def fed(config: GatewayConfig, rate: float, seconds: float,
              ready: Callable[[Gateway], bool], counter: Callable[..., None],
              args: tuple[object, ...], settle: float, through_bus: bool = False) -> Fed:
    """Run the gateway on ``config`` with readings fed at ``rate`` a second (round the
    sensors, moving values; none at 0) and ``counter(*args, seconds, queue)`` in a
    process of its own; measured ``settle`` seconds after the counter started, for
    ``seconds``.

    The readings go into the cache on the event loop; with ``through_bus``, they come
    from the bus thread instead, each in a turn of its own, handed over as a line's
    answers are (``CacheWriter``: at once, or within ``hand_over_ms``)."""
    gw = Gateway(config)
    stop, feeding = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(gw.run(stop))
    while not ready(gw):
        await asyncio.sleep(0.05)

    async def feed() -> None:
        for name, reading, due in _paced(rate):
            if feeding.is_set():
                return
            gw.cache.publish(name, reading)
            await asyncio.sleep(max(0.0, due - time.monotonic()))

    def feed_bus() -> None:  # (a thread of its own: the bus thread's turns it posts)
        writer, reactor = gw.buses.writer, gw.buses.reactor
        for name, reading, due in _paced(rate):
            if feeding.is_set():
                return
            reactor.post(functools.partial(writer.publish, name, reading))
            time.sleep(max(0.0, due - time.monotonic()))

    feeder = asyncio.create_task(asyncio.to_thread(feed_bus) if through_bus else feed())
    results: multiprocessing.Queue[int] = multiprocessing.Queue()
    process = multiprocessing.Process(target=counter, args=(*args, seconds, results))
    process.start()
    await asyncio.sleep(settle)
    # (the total exact; its split into user and system from the kernel's accounting)
    c0, u0, t0 = time.process_time(), _usage(), time.monotonic()
    await asyncio.sleep(seconds)
    cpu, u1, elapsed = time.process_time() - c0, _usage(), time.monotonic() - t0
    delivered = await asyncio.to_thread(results.get, True, 120)
    await asyncio.to_thread(process.join, 30)
    feeding.set()
    await feeder
    stop.set()
    await task
    return Fed(delivered, cpu / elapsed, (u1.ru_stime - u0.ru_stime) / elapsed,
               (u1.ru_nvcsw - u0.ru_nvcsw) / elapsed)


def _paced(rate: float) -> Iterator[tuple[str, Reading, float]]:
    """The fed readings, round the sensors, moving values: (sensor, reading, when the
    next one is due); none at ``rate`` 0 (idle)."""
    if rate <= 0:
        return
    motion, period, start = Motion.from_seed(1), 1.0 / rate, time.monotonic()
    for n in itertools.count():
        yield f"s{n % FED_SENSORS}", motion.sample(n * period), start + (n + 1) * period


def _usage() -> resource.struct_rusage:
    return resource.getrusage(resource.RUSAGE_SELF)
