"""The bus master against simulated sensors on real pseudo-terminals.

The simulator runs on its own thread and counts any byte the master sends while a
sensor is answering (an overlap); every test ends by asserting there were none.
Assertions are about behaviour (what was read, in which order, how the bus time was
shared), never about how fast this machine happens to be.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import time
import tty
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from typing import Any

import pytest
from support.harness import running, until

from imu_gateway.app import Gateway
from imu_gateway.bus import link as link_module
from imu_gateway.bus.link import SerialLink
from imu_gateway.bus.master import OFFLINE_AFTER, BusMaster
from imu_gateway.bus.reactor import Reactor
from imu_gateway.cache import EventKind, Snapshot, Status
from imu_gateway.commands import Command, CommandResult
from imu_gateway.config import config_from_dict
from imu_gateway.errors import ErrorKind, LinkError, RequestFailed
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, SimSensor, SimulatorThread, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
#: For tests about scheduling rather than failures: a hiccup of this busy machine must
#: not turn into a timeout (and a back-off) that the test would then see as unfairness.
PATIENT = {"timeout_ms": 2000}


def bus_config(port: str, protocol: str, sensors: list[dict[str, Any]],
               baudrate: int = FAST, **bus: Any) -> dict[str, Any]:
    return {"gateway_id": "test", "buses": [
        {"name": "line", "port": port, "baudrate": baudrate, "protocol": protocol,
         "sensors": sensors, **bus}]}


def master(gateway: Gateway) -> BusMaster:
    return next(iter(gateway.masters.values()))


def native(series: Series, address: int, **options: Any) -> SimSensor:
    return make_sensor(WireProtocol.NATIVE, series, address, baud=FAST, **options)


def modbus(series: Series, address: int, **options: Any) -> SimSensor:
    return make_sensor(WireProtocol.MODBUS, series, address, baud=FAST, **options)


def no_overlap(sim: SimulatorThread) -> None:
    # each incident with the timed events that led to it
    assert sim.bus.stats.masters_overlaps == 0, "\n".join(
        "\n  ".join(incident) for incident in sim.bus.stats.incidents)
    assert sim.bus.stats.internal_errors == 0


# ------------------------------------------------------------------ readings


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", ["native", "modbus"])
async def test_readings_reach_the_cache_with_the_series_groups(protocol: str) -> None:
    make = native if protocol == "native" else modbus
    first = 0 if protocol == "native" else 1
    with simulated([make(Series.AH, first), make(Series.IMU, first + 1)]) as sim:
        async with running(bus_config(sim.path, protocol, [
            {"name": "ah", "series": "AH", "address": first, "poll_hz": 20},
            {"name": "imu", "series": "IMU", "address": first + 1, "poll_hz": 20},
        ])) as gw:
            await until(lambda: gw.cache.snapshot("ah").seq >= 3
                        and gw.cache.snapshot("imu").seq >= 3)
            ah, imu = gw.cache.snapshot("ah"), gw.cache.snapshot("imu")
            assert ah.status is Status.OK and imu.status is Status.OK
            assert ah.reading is not None and imu.reading is not None
            # (with the values derived from them: tilt from the angles, vibration from
            # the accelerations)
            assert {g.value for g in ah.reading.groups()} == {
                "angles", "accel", "gyro", "mag", "quaternion", "tilt", "vibration"}
            assert {g.value for g in imu.reading.groups()} == {"accel", "gyro", "vibration"}
        no_overlap(sim)


@pytest.mark.parametrize(("protocol", "angle_step", "mag_step"), [
    ("native", 0.005, 0.000005),  # half the BCD resolution: SXXX.YY and S.YYYYY
    ("modbus", 1e-4, 1e-6),  # float32
])
@pytest.mark.anyio
async def test_values_equal_the_simulators_within_resolution(protocol: str, angle_step: float,
                                                        mag_step: float) -> None:
    reading = Motion.from_seed(4).sample(12.0)
    make = native if protocol == "native" else modbus
    address = 0 if protocol == "native" else 1
    with simulated([make(Series.AH, address, source=hold(reading))]) as sim:
        async with running(bus_config(sim.path, protocol, [
            {"name": "ah", "series": "AH", "address": address, "poll_hz": 20}])) as gw:
            await until(lambda: gw.cache.snapshot("ah").seq >= 1)
            got = gw.cache.snapshot("ah").reading
            assert got is not None
            for group, step in (("angles", angle_step), ("accel", 0.00005),
                                ("gyro", 0.005), ("mag", mag_step),
                                ("quaternion", 0.0000005)):
                want = reading.to_json_groups()[group]
                have = got.to_json_groups()[group]
                assert have == pytest.approx(want, abs=step), group
        no_overlap(sim)


# ------------------------------------------------------------------ one at a time


@pytest.mark.anyio
async def test_concurrent_commands_and_polling_never_overlap_and_commands_go_first() -> None:
    sensors = [native(Series.AH, 0), native(Series.VG, 1), native(Series.MINS, 2)]
    with simulated(sensors) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 0},
            {"name": "vg", "series": "VG", "address": 1, "poll_hz": 0},
            {"name": "mins", "series": "MINS", "address": 2, "poll_hz": 0},
        ], **PATIENT)) as gw:
            m = master(gw)
            runner = next(iter(gw.runners.values()))
            await until(lambda: all(gw.cache.snapshot(n).seq > 2 for n in gw.sensors))

            async def on_the_bus(sensor: str) -> tuple[CommandResult, int]:
                """The command, and the readings the bus took meanwhile, counted on
                the bus's own thread (the cache hears of them later)."""
                loop = asyncio.get_running_loop()
                future: asyncio.Future[tuple[CommandResult, int]] = loop.create_future()

                def readings() -> int:
                    return sum(s.stats.readings for s in m.sensors.values())

                def start() -> None:
                    before = readings()

                    def done(result: Any, error: Exception | None) -> None:
                        loop.call_soon_threadsafe(future.set_result,
                                                  (result, readings() - before))

                    m.submit(sensor, Command("read_settings"), done)

                await runner.call(start)
                return await future

            async def submitter(sensor: str, n: int) -> list[bool]:
                oks = []
                for _ in range(n):
                    result, polled = await on_the_bus(sensor)
                    # Commands go before polls: at most the poll in flight when it was
                    # submitted finishes first (other commands may, in order).
                    assert polled <= 1
                    oks.append(result.ok)
                return oks

            results = await asyncio.gather(*(submitter(s, 8) for s in gw.sensors))
            assert all(all(r) for r in results)
            assert m.stats.transactions > 0
        no_overlap(sim)


@pytest.mark.anyio
async def test_identical_on_demand_reads_share_one_exchange() -> None:
    with simulated([native(Series.AH, 0)]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 0.2}])) as gw:
            await until(lambda: gw.cache.snapshot("ah").seq >= 1)
            m = master(gw)
            before = m.stats.transactions
            snaps = await asyncio.wait_for(
                asyncio.gather(*(gw.read("ah", 0) for _ in range(50))), 10)
            assert m.stats.transactions - before == 1
            assert len({s.seq for s in snaps}) == 1
            cached = await gw.read("ah", 60_000)  # young enough: no bus traffic
            assert m.stats.transactions - before == 1 and cached.seq == snaps[0].seq
        no_overlap(sim)


@pytest.mark.anyio
async def test_fast_polling_is_shared_fairly() -> None:
    with simulated([native(Series.IMU, a) for a in range(3)]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": f"s{a}", "series": "IMU", "address": a, "poll_hz": 0}
            for a in range(3)], **PATIENT)) as gw:
            await until(lambda: gw.cache.snapshot("s0").seq >= 60)
            seqs = [gw.cache.snapshot(f"s{a}").seq for a in range(3)]
            assert max(seqs) - min(seqs) <= 1  # strict round robin
        no_overlap(sim)


@pytest.mark.anyio
async def test_asking_more_than_the_wire_slows_every_sensor_evenly_and_counts_the_shortfall(
) -> None:
    # Three AH sensors at 9600 baud: a 0x59 exchange is 62 bytes, 64.6 ms on the wire,
    # so 15 polls/s is the ceiling; 3 x 20 Hz cannot be met.
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, a) for a in range(3)]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": f"s{a}", "series": "AH", "address": a, "poll_hz": 20}
            for a in range(3)], baudrate=9600, **PATIENT)) as gw:
            await until(lambda: gw.cache.snapshot("s0").seq >= 15)
            stats = [master(gw).sensor_stats(f"s{a}") for a in range(3)]
            readings = [s.readings for s in stats]
            assert max(readings) - min(readings) <= 1
            assert all(s.missed_polls > 0 for s in stats)
        no_overlap(sim)


# ------------------------------------------------------------------ failures


@pytest.mark.anyio
async def test_dead_address_costs_the_live_sensors_little_and_comes_back() -> None:
    dead = Faults(stalled=True)
    sensors = [native(Series.AH, 0), native(Series.IMU, 1), native(Series.VG, 2, faults=dead)]
    with simulated(sensors) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 0},
            {"name": "imu", "series": "IMU", "address": 1, "poll_hz": 0},
            {"name": "dead", "series": "VG", "address": 2, "poll_hz": 0},
        ])) as gw:
            m = master(gw)
            # (a probe of the dead sensor comes when the line can spare it: at most 2 % of
            # its time, so a busy machine, whose learned timeouts are longer, spaces them
            # further apart; one probe after it went offline is enough here)
            await until(lambda: gw.cache.snapshot("dead").status is Status.OFFLINE
                        and m.sensors["dead"].failures >= OFFLINE_AFTER + 1, 60)
            # (its share of the bus once backed off: tests/bus/test_schedule.py)
            seq = gw.cache.snapshot("ah").seq
            await until(lambda: gw.cache.snapshot("ah").seq > seq + 10)
            assert gw.cache.snapshot("ah").status is Status.OK
            dead.stalled = False
            await until(lambda: gw.cache.snapshot("dead").status is Status.OK, 40)
        no_overlap(sim)


@pytest.mark.anyio
async def test_offline_is_logged_once_and_recovery_once(
        caplog: pytest.LogCaptureFixture) -> None:
    faults = Faults()
    with simulated([native(Series.AH, 0, faults=faults)]) as sim, \
            caplog.at_level("INFO", logger="imu_gateway"):
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 0}])) as gw:
            await until(lambda: gw.cache.snapshot("ah").status is Status.OK)
            faults.stalled = True
            await until(lambda: gw.cache.snapshot("ah").status is Status.OFFLINE)
            await until(lambda: master(gw).sensors["ah"].failures >= OFFLINE_AFTER + 3, 20)
            faults.stalled = False
            await until(lambda: gw.cache.snapshot("ah").status is Status.OK, 15)
    lines = [r.getMessage() for r in caplog.records if r.name == "imu_gateway.bus"]
    assert sum("offline" in line for line in lines) == 1
    assert sum("recovered" in line for line in lines) == 1


@pytest.mark.anyio
async def test_status_events_follow_the_sensor() -> None:
    faults = Faults()
    with simulated([native(Series.AH, 0, faults=faults)]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 10,
             "stale_after_ms": 300}])) as gw:
            seen: list[Status] = []

            def listen(kind: EventKind, snap: Snapshot) -> None:
                if kind is EventKind.STATUS:
                    seen.append(snap.status)
            gw.cache.subscribe(listen)
            await until(lambda: Status.OK in seen)
            faults.stalled = True
            mark = len(seen)
            await until(lambda: Status.OFFLINE in seen[mark:])
            # stale (no reading for 300 ms) comes before offline (3 failures)
            assert seen[mark:] == [Status.STALE, Status.OFFLINE], seen


@pytest.mark.anyio
async def test_noisy_line_counts_bad_frames_and_keeps_reading() -> None:
    with simulated([native(Series.AH, 0, faults=Faults(corrupt_rate=0.3))], noise_rate=20) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 0}], retries=2)) as gw:
            await until(lambda: gw.cache.snapshot("ah").seq >= 40, 20)
            errors = master(gw).bus_stats().errors
            assert errors.get("bad_frame", 0) > 0
            assert gw.cache.snapshot("ah").errors > 0


@pytest.mark.anyio
async def test_port_removed_and_restored_readings_resume(tmp_path: Any) -> None:
    link = str(tmp_path / "ttyUSB-sim")
    with simulated([native(Series.AH, 0)], link=link) as sim:
        async with running(bus_config(link, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 20}])) as gw:
            m = master(gw)
            await until(lambda: gw.cache.snapshot("ah").seq >= 3)
            sim.call(sim.bus.unplug)
            await until(lambda: gw.cache.snapshot("ah").status is Status.OFFLINE)
            assert not m.port_open
            result = await gw.command("ah", "read_settings")
            assert result.kind is ErrorKind.OFFLINE
            with pytest.raises(RequestFailed):
                await gw.read("ah", 0)
            await asyncio.sleep(1.0)  # several failed reopen attempts
            sim.call(sim.bus.replug)
            seq = gw.cache.snapshot("ah").seq
            await until(lambda: gw.cache.snapshot("ah").seq > seq + 3, 15)
            assert m.bus_stats().errors["port_lost"] == 1
        no_overlap(sim)


@pytest.mark.anyio
async def test_lines_share_the_bus_thread_but_not_their_troubles(
        tmp_path: Any, caplog: pytest.LogCaptureFixture) -> None:
    """Every line runs in one loop on the bus thread: a line whose port is pulled, or
    whose master hits a bug, costs the other line nothing."""
    link = str(tmp_path / "ttyUSB-a")
    with simulated([native(Series.AH, 0)], link=link) as sim_a, \
            simulated([modbus(Series.VG, 1)]) as sim_b:
        config = {"gateway_id": "test", "buses": [
            {"name": "a", "port": link, "baudrate": FAST, "protocol": "native",
             "sensors": [{"name": "ah", "series": "AH", "address": 0, "poll_hz": 0}]},
            {"name": "b", "port": sim_b.path, "baudrate": FAST, "protocol": "modbus",
             "sensors": [{"name": "vg", "series": "VG", "address": 1, "poll_hz": 0}]}]}
        async with running(config) as gw:
            await until(lambda: gw.cache.snapshot("ah").seq >= 3 and
                        gw.cache.snapshot("vg").seq >= 3)
            sim_a.call(sim_a.bus.unplug)
            await until(lambda: gw.cache.snapshot("ah").status is Status.OFFLINE)
            seq = gw.cache.snapshot("vg").seq
            await until(lambda: gw.cache.snapshot("vg").seq >= seq + 20)

            def broken(now: float, pending: int = 0) -> None:
                raise RuntimeError("a bug in line a's schedule")

            gw.masters["a"].schedule.handle_timer = broken  # type: ignore[method-assign]
            sim_a.call(sim_a.bus.replug)  # line a reopens into its bug, again and again
            seq = gw.cache.snapshot("vg").seq
            await until(lambda: gw.cache.snapshot("vg").seq >= seq + 20)
            assert gw.cache.snapshot("vg").status is Status.OK
            await until(lambda: "bus a: internal error" in caplog.text)
        no_overlap(sim_b)


@pytest.mark.anyio
async def test_missing_port_at_start_is_retried_without_exiting(tmp_path: Any) -> None:
    async with running(bus_config(str(tmp_path / "nothing"), "native", [
        {"name": "ah", "series": "AH", "address": 0}])) as gw:
        await asyncio.sleep(1.5)
        assert gw.cache.snapshot("ah").status is Status.OFFLINE
        assert not master(gw).port_open


# ------------------------------------------------------------------ settings


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", ["native", "modbus"])
async def test_save_keeps_the_sensor_busy_then_it_answers(protocol: str) -> None:
    make = native if protocol == "native" else modbus
    address = 0 if protocol == "native" else 1
    with simulated([make(Series.VG, address, save_duration=0.05)]) as sim:
        async with running(bus_config(sim.path, protocol, [
            {"name": "vg", "series": "VG", "address": address, "poll_hz": 20}])) as gw:
            m = master(gw)
            await until(lambda: gw.cache.snapshot("vg").seq >= 2)
            saved = await gw.command("vg", "save")
            assert saved.ok, saved
            assert gw.cache.snapshot("vg").busy
            busy = await gw.command("vg", "read_settings")
            assert busy.kind is ErrorKind.BUSY
            failures = m.bus_stats().errors
            await asyncio.sleep(0.2)  # the simulated save (0.05 s) is over
            # Nothing was sent while saving (checked before the busy period ends: what
            # a loaded machine garbles afterwards is ordinary traffic, not the save's).
            assert m.bus_stats().errors == failures
            m.sensors["vg"].busy_until = 0.01  # the master would wait its 5 s
            await until(lambda: not gw.cache.snapshot("vg").busy)
            after = await gw.command("vg", "read_settings")
            assert after.ok, after
        no_overlap(sim)


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", ["native", "modbus"])
async def test_baud_change_the_gateway_follows(protocol: str) -> None:
    make = make_sensor(WireProtocol[protocol.upper()], Series.AH, 0 if protocol == "native" else 1)
    with simulated([make]) as sim:
        address = make.address
        async with running(bus_config(sim.path, protocol, [
            {"name": "ah", "series": "AH", "address": address, "poll_hz": 10}],
            baudrate=9600)) as gw:
            await until(lambda: gw.cache.snapshot("ah").seq >= 2)
            result = await gw.command("ah", "set_baudrate", {"baudrate": 115200})
            assert result.ok, result
            assert make.baud == 115200 and master(gw).schedule.baud == 115200
            seq = gw.cache.snapshot("ah").seq
            await until(lambda: gw.cache.snapshot("ah").seq >= seq + 3)
            assert sim.bus.line_baud() == 115200
        no_overlap(sim)


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", ["native", "modbus"])
async def test_address_change_answers_at_the_new_address(protocol: str) -> None:
    sensor = make_sensor(WireProtocol[protocol.upper()], Series.VG,
                         0 if protocol == "native" else 1, baud=FAST)
    with simulated([sensor]) as sim:
        async with running(bus_config(sim.path, protocol, [
            {"name": "vg", "series": "VG", "address": sensor.address, "poll_hz": 10}])) \
                as gw:
            await until(lambda: gw.cache.snapshot("vg").seq >= 2)
            result = await gw.command("vg", "set_address", {"address": 42})
            assert result.ok, result
            assert sensor.address == 42
            seq = gw.cache.snapshot("vg").seq
            await until(lambda: gw.cache.snapshot("vg").seq >= seq + 3)
            settings = await gw.command("vg", "read_settings")
            assert settings.answer["address"] == 42
        no_overlap(sim)


@pytest.mark.anyio
async def test_commands_are_validated_and_carried_out() -> None:
    with simulated([native(Series.MINS, 0, source=hold(Motion().sample(0))),
                    modbus(Series.AH, 1)]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "m", "series": "MINS", "address": 0, "poll_hz": 5}])) as gw:
            await until(lambda: gw.cache.snapshot("m").seq >= 1)
            heading = await gw.command("m", "set_relative_heading", {"degrees": 90})
            assert heading.ok, heading
            snap = await gw.read("m", 0)
            assert snap.reading is not None and snap.reading.angles is not None
            assert snap.reading.angles.yaw == pytest.approx(90.0, abs=0.01)
            bad = await gw.command("m", "set_relative_heading", {"degrees": "north"})
            assert bad.kind is ErrorKind.BAD_ARGUMENTS
            lacking = await gw.command("m", "set_declination", {"degrees": 2})
            assert lacking.kind is ErrorKind.UNSUPPORTED
            unknown = await gw.command("m", "self_destruct")
            assert unknown.kind is ErrorKind.UNKNOWN_COMMAND
            nobody = await gw.command("nobody", "save")
            assert nobody.kind is ErrorKind.UNKNOWN_SENSOR
        no_overlap(sim)


@pytest.mark.anyio
async def test_modbus_gyro_calibration_is_busy_until_done() -> None:
    with simulated([modbus(Series.VG, 1, gyro_cal_duration=0.5)]) as sim:
        async with running(bus_config(sim.path, "modbus", [
            {"name": "vg", "series": "VG", "address": 1, "poll_hz": 10}])) as gw:
            await until(lambda: gw.cache.snapshot("vg").seq >= 1)
            result = await gw.command("vg", "calibrate_gyro")
            assert result.ok and result.answer == {"value": 0}  # 0 = started
            assert gw.cache.snapshot("vg").busy
            # cleared by the sensor's "done" (0.5 s), not the master's 10 s fallback
            await until(lambda: not gw.cache.snapshot("vg").busy, 5)
        no_overlap(sim)


# ------------------------------------------------------------------ auto-output


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", ["native", "modbus"])
async def test_stream_feeds_the_cache_commands_still_work_and_polling_takes_over(
        protocol: str) -> None:
    faults = Faults()
    sensor = make_sensor(WireProtocol[protocol.upper()], Series.AH,
                         0 if protocol == "native" else 1, baud=FAST, faults=faults)
    with simulated([sensor]) as sim:
        async with running(bus_config(sim.path, protocol, [
            {"name": "ah", "series": "AH", "address": sensor.address, "poll_hz": 5,
             "stream_hz": 50}])) as gw:
            m = master(gw)
            await until(lambda: gw.cache.snapshot("ah").streaming)
            polls = m.stats.transactions
            seq = gw.cache.snapshot("ah").seq
            await until(lambda: gw.cache.snapshot("ah").seq >= seq + 20)
            assert m.stats.transactions == polls  # readings came without asking
            result = await gw.command("ah", "read_settings")
            assert result.ok, result
            # the stream stops (say the sensor was power-cycled): polling takes over
            faults.stalled = True
            await until(lambda: not gw.cache.snapshot("ah").streaming, 5)
            faults.stalled = False
            sensor.stream_interval = 0.0  # it came back in answer mode: set it up again
            await until(lambda: gw.cache.snapshot("ah").streaming, 15)
        no_overlap(sim)


@pytest.mark.anyio
async def test_stream_is_stopped_on_shutdown() -> None:
    sensor = native(Series.VG, 0)
    with simulated([sensor]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "vg", "series": "VG", "address": 0, "stream_hz": 20}])) as gw:
            await until(lambda: gw.cache.snapshot("vg").streaming)
        assert sensor.stream_interval == 0.0


@pytest.mark.anyio
async def test_on_demand_reads_of_an_offline_sensor_fail_at_once() -> None:
    """Asking a dead sensor on demand would undo its back-off: it is refused at once."""
    with simulated([native(Series.AH, 0), native(Series.VG, 1, faults=Faults(stalled=True))]) \
            as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 0},
            {"name": "dead", "series": "VG", "address": 1, "poll_hz": 0}])) as gw:
            m = master(gw)
            # offline after 3 failed exchanges, the probes among them spaced for the
            # line's probe budget: 10-20 s at idle, longer on a busy machine
            await until(lambda: m.sensors["dead"].online is False, 60)
            before = m.sensors["dead"].stats.transactions + sum(
                m.sensors["dead"].stats.errors.values())
            for _ in range(20):
                with pytest.raises(RequestFailed) as refused:
                    await gw.read("dead", 0)
                assert refused.value.kind is ErrorKind.OFFLINE
            result = await gw.command("dead", "read_settings")
            assert result.kind is ErrorKind.OFFLINE
            after = m.sensors["dead"].stats.transactions + sum(
                m.sensors["dead"].stats.errors.values())
            assert after - before <= 2  # only its background retries, if one fell due
        no_overlap(sim)


@pytest.mark.anyio
async def test_a_command_during_shutdown_is_answered() -> None:
    with simulated([native(Series.AH, 0)]) as sim:
        gateway = Gateway(config_from_dict(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 0}]), env={}))
        stop = asyncio.Event()
        task = asyncio.create_task(gateway.run(stop))
        await until(lambda: gateway.cache.snapshot("ah").seq >= 1)
        commands = [asyncio.create_task(gateway.command("ah", "read_settings"))
                    for _ in range(5)]
        stop.set()
        results = await asyncio.wait_for(asyncio.gather(*commands), 15)
        await asyncio.wait_for(task, 15)
        assert all(r.ok or r.kind is ErrorKind.OFFLINE for r in results)
        late = await asyncio.wait_for(gateway.command("ah", "read_settings"), 5)
        assert late.kind is ErrorKind.OFFLINE


@pytest.mark.anyio
async def test_a_stream_nobody_asked_for_is_stopped() -> None:
    sensor = native(Series.VG, 0)
    sensor.stream_interval = 0.02  # left streaming at 50 Hz by an earlier owner
    with simulated([sensor]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "vg", "series": "VG", "address": 0, "poll_hz": 10}])) as gw:
            await until(lambda: sensor.stream_interval == 0.0, 10)
            seq = gw.cache.snapshot("vg").seq
            await until(lambda: gw.cache.snapshot("vg").seq >= seq + 3)  # polled again
            assert master(gw).bus_stats().errors["unexpected_frame"] >= 1


@pytest.mark.anyio
async def test_a_stream_that_comes_back_by_itself_is_no_longer_polled() -> None:
    """Its first frame back may meet a poll on the wire (nobody can know it is coming);
    from then on the gateway listens instead of polling."""
    faults = Faults()
    sensor = native(Series.AH, 0, faults=faults)
    with simulated([sensor]) as sim:
        async with running(bus_config(sim.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 20,
             "stream_hz": 50}])) as gw:
            await until(lambda: gw.cache.snapshot("ah").streaming)
            faults.stalled = True
            await until(lambda: not gw.cache.snapshot("ah").streaming, 5)
            faults.stalled = False  # still in auto-output mode: its frames come back
            await until(lambda: gw.cache.snapshot("ah").streaming, 5)
            overlaps = sim.bus.stats.masters_overlaps
            polls = master(gw).stats.transactions
            seq = gw.cache.snapshot("ah").seq
            await until(lambda: gw.cache.snapshot("ah").seq >= seq + 25)
            assert master(gw).stats.transactions == polls
            assert sim.bus.stats.masters_overlaps == overlaps


@contextlib.contextmanager
def bus_thread() -> Iterator[Reactor]:
    reactor = Reactor("test bus")
    reactor.start()
    try:
        yield reactor
    finally:
        reactor.end()
        assert reactor.join(5)
        reactor.close()


def open_link(reactor: Reactor, link: SerialLink, on_bytes: Callable[[bytes, float], None],
              ) -> LinkError | None:
    """Open ``link`` on the bus thread; the error, if it failed."""
    opened: Future[LinkError | None] = Future()
    reactor.post(lambda: link.open(reactor, on_bytes, lambda exc: None, opened.set_result))
    return opened.result(10)


@pytest.mark.parametrize("port", ["pty", "socket://127.0.0.1:9"])
def test_kernel_rs485_mode_where_it_cannot_work_is_a_clear_error(port: str) -> None:
    def refused(path: str) -> None:
        link = SerialLink(path, 9600, rs485=True)
        with bus_thread() as reactor:
            error = open_link(reactor, link, lambda data, at: None)
        assert isinstance(error, LinkError) and re.search(r"RS-?485", str(error))
        assert not link.is_open

    if port == "pty":
        with simulated([native(Series.AH, 0)]) as sim:
            refused(sim.path)
    else:
        refused(port)


@pytest.mark.parametrize("watched", [True, False], ids=["bus loop reads", "reader thread"])
def test_bytes_on_their_way_count_as_pending_until_the_master_has_them(
        watched: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """A busy machine's timer can run before bytes that came: ``pending`` must count
    them (in the port, or read by a reader thread and posted to the held loop), or an
    answer that came is called missing."""
    if not watched:
        monkeypatch.setattr(link_module, "watchable", lambda ser: False)
    master, slave = os.openpty()
    tty.setraw(slave)
    got: list[bytes] = []
    try:
        link = SerialLink(os.ttyname(slave), 115200)
        with bus_thread() as reactor:
            assert open_link(reactor, link, lambda data, at: got.append(data)) is None
            assert link.watched is watched

            def held() -> int:
                """On the bus thread, which is held here: nothing reaches on_bytes."""
                os.write(master, b"\x77\x04\x00\x04\x08")
                deadline = time.monotonic() + 10
                while link.pending() < 5:
                    assert time.monotonic() < deadline
                    time.sleep(0.001)
                return len(got)

            assert reactor.call(held).result(15) == 0
            # (until all five are in: a reader thread may have read them in two parts,
            # the first already posted while the rest waited in the port)
            deadline = time.monotonic() + 10
            while len(b"".join(got)) < 5:
                assert time.monotonic() < deadline
                time.sleep(0.001)
            assert b"".join(got) == b"\x77\x04\x00\x04\x08"
            assert reactor.call(link.pending).result(5) == 0
            reactor.post(link.close)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.anyio
async def test_a_modbus_line_asks_the_port_for_pending_bytes_only_when_they_matter(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The turn after an answer's silent interval, with nothing in flight, decides
    nothing by the bytes in the port: it writes the next request without asking the
    driver (an ioctl per exchange, a tenth of the CPU an exchange costs)."""
    asked = 0
    pending = SerialLink.pending

    def counted(self: SerialLink) -> int:
        nonlocal asked
        asked += 1
        return pending(self)

    monkeypatch.setattr(SerialLink, "pending", counted)
    with simulated([modbus(Series.AH, 1)]) as sim:
        async with running(bus_config(sim.path, "modbus", [
            {"name": "ah", "series": "AH", "address": 1, "poll_hz": 0},
        ], **PATIENT)) as gw:
            await until(lambda: master(gw).stats.transactions >= 200)
            done = master(gw).stats.transactions
            assert gw.cache.snapshot("ah").status is Status.OK
        # (a deadline reached before its answer was in still asks: a busy machine)
        assert asked < done / 4, f"asked {asked} times in {done} exchanges"
        no_overlap(sim)


@pytest.mark.anyio
async def test_a_bug_costs_one_request_not_the_bus(monkeypatch: pytest.MonkeyPatch,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    from imu_gateway.bus.outcomes import Outcomes

    real = Outcomes._done
    failed: list[bool] = []

    def broken_once(self: Outcomes, job: Any, at: float) -> None:
        if not failed:
            failed.append(True)
            raise RuntimeError("a bug in the schedule")
        real(self, job, at)

    monkeypatch.setattr(Outcomes, "_done", broken_once)
    with simulated([native(Series.AH, 0)]) as sim:
        with caplog.at_level("ERROR", logger="imu_gateway.bus"):
            async with running(bus_config(sim.path, "native", [
                {"name": "ah", "series": "AH", "address": 0, "poll_hz": 20}])) as gw:
                await until(lambda: gw.cache.snapshot("ah").seq >= 1)
                first = await gw.command("ah", "read_settings")  # meets the bug
                assert not first.ok and first.kind is ErrorKind.OFFLINE
                assert "internal error" in (first.error or "")
                second = await gw.command("ah", "read_settings")
                assert second.ok, second
                seq = gw.cache.snapshot("ah").seq
                await until(lambda: gw.cache.snapshot("ah").seq >= seq + 3)
        no_overlap(sim)
    assert any("a bug in the schedule" in r.getMessage() or r.exc_info for r in caplog.records)


@pytest.mark.anyio
async def test_a_bug_before_a_request_is_queued_answers_its_asker(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The request fails before the bus master has queued it (a bug in its checks):
    whoever asked gets a failure at once, not a wait for ever, and the next works."""
    from imu_gateway.bus.master import BusMaster

    real = BusMaster.submit
    failed: list[bool] = []

    def broken_once(self: BusMaster, sensor: str, command: Any, done: Any) -> None:
        if not failed:
            failed.append(True)
            raise RuntimeError("a bug before the queue")
        real(self, sensor, command, done)

    monkeypatch.setattr(BusMaster, "submit", broken_once)
    with simulated([native(Series.AH, 0)]) as sim:
        async with running(bus_config(sim.path, "native", [
                {"name": "ah", "series": "AH", "address": 0, "poll_hz": 20}])) as gw:
            await until(lambda: gw.cache.snapshot("ah").seq >= 1)
            first = await asyncio.wait_for(gw.command("ah", "read_settings"), 30)
            assert not first.ok and first.kind is ErrorKind.FAILURE, first
            assert "internal error" in (first.error or "")
            second = await gw.command("ah", "read_settings")
            assert second.ok, second
