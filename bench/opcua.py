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
import tempfile
from dataclasses import dataclass

from asyncua import Client, ua
from common import FED_SENSORS, fed, fed_config, free_port

from imu_gateway.model import VALUE_GROUPS

FIELDS = [f"{spec.title}.{name}" for spec in VALUE_GROUPS.values() for name in spec.fields]
SENSORS = FED_SENSORS


@dataclass(frozen=True)
class Case:
    rate: float  # samples/s, over all sensors
    clients: int
    items: int  # monitored values per client


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
    """asyncua clients, ``case.clients`` of them: their notifications in ``seconds``."""
    logging.getLogger("asyncua").setLevel(logging.ERROR)  # (it warns of revised values)
    counts = [0] * case.clients

    async def main() -> None:
        await asyncio.gather(*(_subscriber(url, case.items, seconds, counts, i)
                               for i in range(case.clients)))

    asyncio.run(main())
    out.put(sum(counts))


async def run_case(case: Case, seconds: float, pki: str) -> tuple[float, float, float]:
    port = free_port()
    config = fed_config(opcua={"listen": f"127.0.0.1:{port}", "allow_none": True,
                               "pki_dir": pki})
    delivered, cores, *_ = await fed(
        config, case.rate, seconds, lambda gw: gw.opcua is not None and gw.opcua.listening,
        _clients, (f"opc.tcp://127.0.0.1:{port}/", case), settle=1.5)
    return delivered / seconds, cores, cores / case.rate


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
