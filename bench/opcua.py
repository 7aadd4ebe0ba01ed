"""The OPC UA server under load: subscribers × monitored items against the sample rate.

The gateway runs its OPC UA server alone, on AH sensors whose readings are put into
the cache at a set rate (as the bus masters would, without their serial lines, so
that the rate is the benchmark's to choose). asyncua clients in a process of their
own (the same 2 cores) subscribe, each to ``items`` values of the sensors, with a
50 ms publishing interval, and count the notifications.  Printed per case: the
samples/s put in, the notifications/s expected (every monitored value changes with
every sample) and delivered, their ratio, and the gateway's CPU (process time ÷
wall time, and per sample).  A ratio under 0.95 is where it stops keeping up.

Run: ``.venv/bin/python bench/opcua.py [--seconds 5]``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import multiprocessing
import os
import socket
import tempfile
import time
from dataclasses import dataclass

from asyncua import Client, ua

from imu_gateway.app import Gateway
from imu_gateway.config import config_from_dict
from imu_gateway.model import VALUE_GROUPS
from imu_gateway.simulator.motion import Motion

FIELDS = [f"{spec.title}.{name}" for spec in VALUE_GROUPS.values() for name in spec.fields]
SENSORS = 4


@dataclass(frozen=True)
class Case:
    rate: float  # samples/s, over all sensors
    clients: int
    items: int  # monitored values per client


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def _subscriber(url: str, items: int, seconds: float, counts: list[int], i: int) -> None:
    class Handler:
        def datachange_notification(self, node: object, val: object, data: object) -> None:
            counts[i] += 1

    async with Client(url, timeout=30) as client:
        idx = await client.get_namespace_index("urn:imu-gateway")
        nodes = [client.get_node(ua.NodeId(
            f"bench.Sensors.s{k % SENSORS}.{FIELDS[(k // SENSORS) % len(FIELDS)]}", idx))
            for k in range(items)]
        subscription = await client.create_subscription(50, Handler())
        await subscription.subscribe_data_change(nodes)
        await asyncio.sleep(1.0)  # the initial values are in
        counts[i] = 0
        await asyncio.sleep(seconds)
        await subscription.delete()


def _clients(url: str, case: Case, seconds: float, out: multiprocessing.Queue[int]) -> None:
    logging.getLogger("asyncua").setLevel(logging.ERROR)  # (it warns of revised values)
    counts = [0] * case.clients

    async def main() -> None:
        await asyncio.gather(*(_subscriber(url, case.items, seconds, counts, i)
                               for i in range(case.clients)))

    asyncio.run(main())
    out.put(sum(counts))


async def _feed(gw: Gateway, rate: float, stop: asyncio.Event) -> None:
    """Readings into the cache at ``rate`` a second, round the sensors, each a new
    sample of moving values."""
    motion = Motion.from_seed(1)
    period, n, start = 1.0 / rate, 0, time.monotonic()
    while not stop.is_set():
        gw.cache.publish(f"s{n % SENSORS}", motion.sample(n * period))
        n += 1
        await asyncio.sleep(max(0.0, start + n * period - time.monotonic()))


async def run_case(case: Case, seconds: float, pki: str) -> tuple[float, float, float]:
    port = _free_port()
    config = config_from_dict({
        "gateway_id": "bench",
        "buses": [{"name": "a", "port": "/dev/null-bench", "baudrate": 115200,
                   "protocol": "native",
                   "sensors": [{"name": f"s{i}", "series": "AH", "address": i,
                                "poll_hz": 1} for i in range(SENSORS)]}],
        "opcua": {"listen": f"127.0.0.1:{port}", "allow_none": True, "pki_dir": pki}},
        env={})
    gw = Gateway(config)
    stop, feeding = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(gw.run(stop))
    while gw.opcua is None or not gw.opcua.listening:
        await asyncio.sleep(0.05)
    feeder = asyncio.create_task(_feed(gw, case.rate, feeding))
    results: multiprocessing.Queue[int] = multiprocessing.Queue()
    clients = multiprocessing.Process(target=_clients, args=(
        f"opc.tcp://127.0.0.1:{port}/", case, seconds, results))
    clients.start()
    await asyncio.sleep(1.5)  # they connect and subscribe (measured from here on)
    c0, t0 = time.process_time(), time.monotonic()
    await asyncio.sleep(seconds)
    cpu, elapsed = time.process_time() - c0, time.monotonic() - t0
    delivered = await asyncio.to_thread(results.get, True, 120)
    await asyncio.to_thread(clients.join, 30)
    feeding.set()
    await feeder
    stop.set()
    await task
    return delivered / seconds, cpu / elapsed, cpu / (case.rate * elapsed)


def main() -> None:
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    logging.getLogger("imu_gateway").setLevel(logging.ERROR)  # the port it cannot open
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    cases = [Case(rate, clients, items)
             for rate in (40, 200, 800) for clients, items in ((1, 16), (5, 16), (20, 16),
                                                             (5, 64))]
    print(f"OPC UA, {SENSORS} AH sensors, publishing interval 50 ms, "
          f"{args.seconds:g} s per case, {os.cpu_count()} CPUs")
    print(f"{'samples/s':>9} {'clients':>7} {'items':>5} {'expected/s':>10} "
          f"{'delivered/s':>11} {'ratio':>5} {'gw cores':>8} {'gw ms/sample':>12}")
    with tempfile.TemporaryDirectory() as pki:
        for case in cases:
            delivered, cores, per_sample = asyncio.run(run_case(case, args.seconds, pki))
            # each client's items spread over the sensors: an item changes with every
            # sample of its sensor
            expected = case.clients * case.items * case.rate / SENSORS
            print(f"{case.rate:>9g} {case.clients:>7} {case.items:>5} {expected:>10.0f} "
                  f"{delivered:>11.0f} {delivered / expected:>5.2f} {cores:>8.3f} "
                  f"{1000 * per_sample:>12.3f}", flush=True)


if __name__ == "__main__":
    main()
