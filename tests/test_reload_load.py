"""A reload under load (docs/configuration.md, "Changing the config while running";
docs/bus-master.md, "A sensor added or removed by a reload"): a sensor added to a
running bus, then removed again.  Modbus TCP and REST pollers of an unchanged sensor
on that bus, and of one on another bus, see no new reading come later than their
normal period (measured before, in the same run; the time the machine kept the
loop waiting for a CPU is not the reload's, ``LoopWatch``); the simulator, which sees each
open and close of its port (``watch_port``), saw each line's port opened once and
never closed."""

from __future__ import annotations

import asyncio
import itertools
import os
import threading
from collections.abc import Awaitable, Callable
from typing import Any

import httpx
import pytest
from pymodbus.client import AsyncModbusTcpClient
from support.harness import free_port, running, until

from imu_gateway.config import config_from_dict
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
RATE = 20  # polls a second of each sensor: a new reading every 50 ms
LOOK_EVERY = 0.005  # how often a poller asks (well inside a period)
#: new readings each poller sees before the reloads (its normal period: the longest
#: gap between two of them), and after each reload
BEFORE, AFTER = 100, 20
#: Beside CPU burners a period now and then comes late by more than the poller's
#: look; "no longer than the normal period" allows the longest seen before, with this
#: much of it again as the machine's wobble.
WOBBLE = 1.5
READING = Motion.from_seed(5).sample(3.0)

Seq = Callable[[], Awaitable[int]]


class Poller:
    """A client asking for a sensor's reading every ``LOOK_EVERY``: when each new one
    (a new ``seq``) was first seen."""

    def __init__(self, name: str, seq: Seq) -> None:
        self.name = name
        self.seq = seq
        self.seen: list[float] = []
        #: what failed, and when (loop time): the failure says whether a reload was on
        self.errors: list[tuple[float, str]] = []

    async def run(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        last = -1
        while not stop.is_set():
            try:
                seq = await self.seq()
            except Exception as exc:  # (kept, and failed on below: a gap in service)
                self.errors.append((loop.time(), f"{type(exc).__name__}: {exc}"))
                seq = last
            if seq != last:
                self.seen.append(loop.time())
                last = seq
            await asyncio.sleep(LOOK_EVERY)

    def longest_gap(self, since: int, held: LoopWatch) -> float:
        """The longest wait for a new reading since the ``since``-th, less the time the
        loop's thread waited for a CPU in it (as ``gap_across``)."""
        return max((b - a) - held.off_cpu(a, b)
                   for a, b in itertools.pairwise(self.seen[since:]))

    def gap_across(self, began: float, ended: float, held: LoopWatch) -> tuple[float, float]:
        """The longest wait for a new reading that overlaps ``began``-``ended`` (the
        reload), less the time the loop's thread waited for a CPU in it (``held``):
        what the reload cost this poller; and that time.  (A stall of the machine well
        after it is not the reload's: beside CPU burners one came a second late, 20
        readings on.)"""
        return max((max(0.0, (b - a) - (off := held.off_cpu(a, b))), off)
                   for a, b in itertools.pairwise(self.seen) if b >= began and a <= ended)


class LoopWatch:
    """When the loop's thread was runnable but kept waiting for a CPU: the machine's
    doing (CPU burners), not the gateway's.  The kernel counts that wait for each
    thread (``/proc/self/task/TID/schedstat``, its second field, ns); a task notes it
    every ``LOOK_EVERY``.  A thread blocked in a call (a sleep, a lock) is not waiting
    for a CPU: a reload that blocked the loop would still be caught."""

    def __init__(self) -> None:
        self.waits: list[tuple[float, float, float]] = []  # (from, to, seconds waited)

    async def run(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        path = f"/proc/self/task/{threading.get_native_id()}/schedstat"
        if not os.path.exists(path):  # (a kernel without CONFIG_SCHED_INFO)
            print(f"no {path}: no wait for a CPU is taken off the gaps")
            return
        with open(path) as stat:
            def waited() -> float:
                stat.seek(0)
                return int(stat.read().split()[1]) / 1e9

            wall, wait = loop.time(), waited()
            while not stop.is_set():
                await asyncio.sleep(LOOK_EVERY)
                now, then = loop.time(), waited()
                self.waits.append((wall, now, then - wait))
                wall, wait = now, then

    def off_cpu(self, start: float, end: float) -> float:
        """The wait within ``start``-``end``: of a look only partly inside, its share."""
        return sum(w * (min(b, end) - max(a, start)) / (b - a)
                   for a, b, w in self.waits if a < end and b > start and b > a)


def native_line(addresses: list[int]) -> list[Any]:
    return [make_sensor(WireProtocol.NATIVE, Series.AH, address=a, baud=FAST,
                        source=hold(READING)) for a in addresses]


def config(line_a: str, line_b: str, http: int, with_arm2: bool) -> dict[str, Any]:
    def ah(name: str, address: int, unit: int) -> dict[str, Any]:
        return {"name": name, "series": "AH", "address": address, "unit_id": unit,
                "poll_hz": RATE}

    b = [ah("arm", 0, 2)] + ([ah("arm2", 1, 3)] if with_arm2 else [])
    return {"gateway_id": "load", "modbus": {"listen": "127.0.0.1:0"},
            "http": {"listen": f"127.0.0.1:{http}"},
            "buses": [{"name": "a", "port": line_a, "protocol": "native", "baudrate": FAST,
                       "sensors": [ah("boom", 0, 1)]},
                      {"name": "b", "port": line_b, "protocol": "native", "baudrate": FAST,
                       "sensors": b}]}


@pytest.mark.anyio
async def test_a_sensor_added_and_removed_under_load_costs_the_others_no_reading() -> None:
    http = free_port()
    with simulated(native_line([0]), watch_port=True) as sim_a, \
            simulated(native_line([0, 1]), watch_port=True) as sim_b:
        first = config(sim_a.path, sim_b.path, http, with_arm2=False)
        async with running(first) as gw, \
                AsyncModbusTcpClient("127.0.0.1", port=gw.modbus.port if gw.modbus else 0) \
                as modbus, httpx.AsyncClient(base_url=f"http://127.0.0.1:{http}") as rest:

            def by_modbus(unit: int) -> Seq:
                async def seq() -> int:
                    answer = await modbus.read_input_registers(2, count=2, device_id=unit)
                    assert not answer.isError(), answer
                    return int(answer.registers[0] << 16 | answer.registers[1])
                return seq

            def by_rest(name: str) -> Seq:
                async def seq() -> int:
                    answer = await rest.get(f"/api/v1/sensors/{name}/reading")
                    answer.raise_for_status()
                    return int(answer.json()["seq"])
                return seq

            pollers = [Poller("modbus arm (bus b)", by_modbus(2)),
                       Poller("modbus boom (bus a)", by_modbus(1)),
                       Poller("rest arm (bus b)", by_rest("arm")),
                       Poller("rest boom (bus a)", by_rest("boom"))]
            # Each sensor read once before anyone asks: a REST reading before the first
            # is a 503 (not read yet), which is the start-up's, not a reload's.
            await until(lambda: all(gw.cache.snapshot(n).has_reading for n in ("arm", "boom")),
                        30)
            stop = asyncio.Event()
            reloads: list[tuple[float, float]] = []
            held = LoopWatch()
            tasks = [asyncio.create_task(p.run(stop)) for p in pollers] + \
                [asyncio.create_task(held.run(stop))]
            try:
                await until(lambda: all(len(p.seen) > 5 for p in pollers), 30)
                start = {p.name: len(p.seen) - 1 for p in pollers}  # (past the start-up)
                await until(lambda: all(len(p.seen) > start[p.name] + BEFORE
                                        for p in pollers), 60)
                normal = {p.name: p.longest_gap(start[p.name], held) for p in pollers}
                for with_arm2 in (True, False):
                    marks = {p.name: len(p.seen) - 1 for p in pollers}
                    began = asyncio.get_running_loop().time()
                    diff = await gw.reloader._apply(config_from_dict(
                        config(sim_a.path, sim_b.path, http, with_arm2), env={}))
                    took = asyncio.get_running_loop().time()
                    reloads.append((began, took))
                    assert diff.buses_rescheduled == ("b",) and diff.buses_restarted == ()
                    assert "its schedule only" in diff.summary(), diff.summary()
                    if with_arm2:
                        await until(lambda: gw.cache.snapshot("arm2").has_reading)
                        assert 3 in gw.modbus.units if gw.modbus else False
                    else:
                        assert "arm2" not in gw.masters["b"].sensors
                    await until(lambda m=marks: all(  # type: ignore[misc]
                        len(p.seen) > m[p.name] + AFTER for p in pollers), 30)
                    # every poller's figures first: a failure shows whether one bus
                    # or all of them (the machine, the gateway's loop) were held
                    across = {p.name: p.gap_across(began, took, held) for p in pollers}
                    lines = [f"{'+' if with_arm2 else '-'}arm2: {name}: normal "
                             f"{normal[name] * 1000:.0f} ms, across the reload "
                             f"{gap * 1000:.0f} ms and {off * 1000:.0f} ms of the loop "
                             f"waiting for a CPU (the reload took "
                             f"{(took - began) * 1000:.0f} ms)"
                             for name, (gap, off) in across.items()]
                    print("\n".join(lines))
                    assert all(gap <= WOBBLE * normal[name]
                               for name, (gap, _) in across.items()), lines
                for sim in (sim_a, sim_b):  # the simulator's own log of its port
                    assert (sim.bus.stats.port_opens, sim.bus.stats.port_closes) == (1, 0), \
                        [e for e in sim.bus.stats.events if e.startswith("PORT")]
            finally:
                stop.set()
                await asyncio.gather(*tasks)
            assert [p.errors for p in pollers] == [[]] * 4, ("the reloads", reloads)
