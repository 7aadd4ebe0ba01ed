"""Sensors that answer sooner than the Modbus serial-line rule allows, with the real
gateway on the simulator's pseudo-terminal: idle, and beside CPU burners.

At 9600 baud RTU's 3.5-character gap is 3.65 ms; many real sensors answer 0-2 ms after
the request's last byte.  Such an answer matches its request and is its answer
(docs/bus-master.md, "Timing and timeouts").  The tests wait for polls taken, never
for a fixed time.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator

import httpx
import pytest
from pymodbus.client import AsyncModbusTcpClient
from support.harness import running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

POLLS = 14  # as many as the emulator's run that found the bug
#: Each burner ends by itself after this long, should the test not end it.
BURN_MAX_S = 120
BURN = f"import time\nt = time.monotonic() + {BURN_MAX_S}\nwhile time.monotonic() < t: pass"


@contextlib.contextmanager
def burners(count: int) -> Iterator[None]:
    """``count`` processes that keep a core busy each, bounded, killed at the end."""
    procs = [subprocess.Popen([sys.executable, "-c", BURN]) for _ in range(count)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", ["native", "modbus"])
@pytest.mark.parametrize("delay_ms", [0.0, 0.5, 2.0])
@pytest.mark.parametrize("load", [0, 2])
async def test_answers_inside_the_gap_are_taken_idle_and_loaded(
        protocol: str, delay_ms: float, load: int) -> None:
    """A VG at 9600 baud answering ``delay_ms`` after the request's last byte (Modbus
    without the RTU gap): every poll is taken, the sensor stays online, nothing talks
    over an answer, and on an idle machine not one answer is counted as missing."""
    proto = WireProtocol[protocol.upper()]
    address = 0 if proto is WireProtocol.NATIVE else 1
    vg = make_sensor(proto, Series.VG, address, baud=9600, answer_delay=delay_ms / 1000,
                     keep_gap=False)
    with burners(load), simulated([vg]) as sim:
        async with running({"gateway_id": "test", "buses": [
                {"name": "line", "port": sim.path, "baudrate": 9600, "protocol": protocol,
                 "sensors": [{"name": "vg", "series": "VG", "address": address,
                              "poll_hz": 20}]}]}) as gw:
            await until(lambda: gw.sensor_stats("vg").readings >= POLLS, 30)
            stats = gw.sensor_stats("vg")
        assert stats.online and stats.readings >= POLLS
        assert sim.bus.stats.masters_overlaps == 0
        if not load:  # idle: not one answer missed
            assert stats.errors.get("timeout", 0) == 0, stats
        # (early_answers is judged from a read's times, late on a pty: not asserted here,
        # but in test_schedule.py's virtual time)
        print(f"{protocol} {delay_ms} ms load {load}: readings {stats.readings}, "
              f"transactions {stats.transactions}, early {stats.early_answers}, "
              f"errors {dict(stats.errors)}")


@pytest.mark.anyio
@pytest.mark.parametrize("lost", [False, True])
async def test_a_modbus_tcp_write_is_sent_once_and_a_lost_answer_is_unconfirmed(
        lost: bool) -> None:
    """The issue's worst case: a Modbus TCP client writes 1 (relative) to register
    1000 of a VG that answers 0.5 ms after the request.  The sensor hears the write
    once, whether its acknowledgement comes (a normal answer) or is lost (exception
    04, "unconfirmed: read the setting back"; never 0B, never a second write)."""
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=9600, answer_delay=0.0005,
                     keep_gap=False)
    with simulated([vg]) as sim:
        async with running({"gateway_id": "test", "modbus": {"listen": "127.0.0.1:0",
                                                            "allow_writes": True},
                            "buses": [{"name": "line", "port": sim.path, "baudrate": 9600,
                                       "protocol": "modbus", "retries": 2, "sensors": [
                                           {"name": "vg", "series": "VG", "address": 1,
                                            "poll_hz": 5}]}]}) as gw:
            await until(lambda: gw.sensor_stats("vg").readings >= 2, 30)
            vg.faults.drop_rate = 1.0 if lost else 0.0
            before = sum(vg.writes_heard.values())
            assert gw.modbus is not None
            client = AsyncModbusTcpClient("127.0.0.1", port=gw.modbus.port, timeout=10,
                                          retries=0)
            assert await client.connect()
            try:
                rr = await client.write_register(1000, 1, device_id=1)
            finally:
                client.close()
            vg.faults.drop_rate = 0.0
            await until(lambda: gw.sensor_stats("vg").readings >= 4, 30)  # the line went on
        assert sum(vg.writes_heard.values()) == before + 1
        if lost:
            assert rr.isError() and rr.exception_code == 0x04, rr
        else:
            assert not rr.isError(), rr
        assert sim.bus.stats.masters_overlaps == 0


@pytest.mark.anyio
async def test_early_answers_are_shown_per_sensor_and_per_bus() -> None:
    """``early_answers`` is in the REST bus list (the bus's total and each sensor's
    timing) and in /metrics, as the late answers are (docs/rest.md)."""
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=9600, answer_delay=0.0,
                     keep_gap=False)
    with simulated([vg]) as sim:
        async with running({"gateway_id": "test", "http": {"listen": "127.0.0.1:0"},
                            "buses": [{"name": "line", "port": sim.path, "baudrate": 9600,
                                       "protocol": "modbus", "sensors": [
                                           {"name": "vg", "series": "VG", "address": 1,
                                            "poll_hz": 20}]}]}) as gw:
            await until(lambda: gw.sensor_stats("vg").readings >= POLLS, 30)
            assert gw.http is not None
            async with httpx.AsyncClient(
                    base_url=f"http://127.0.0.1:{gw.http.port}", timeout=10) as http:
                buses = (await http.get("/api/v1/buses")).json()
                metrics = (await http.get("/metrics")).text
    (line,) = buses
    early = line["timing"]["vg"]["early_answers"]
    # (the two are read one after the other while polls go on: either may be ahead)
    assert isinstance(early, int) and early >= 0 and line["early_answers"] >= 0
    assert 'imu_gateway_sensor_early_answers_total{sensor="vg"}' in metrics
