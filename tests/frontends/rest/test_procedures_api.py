"""The wizards as REST procedures (docs/wizards.md, docs/rest.md "Procedures"), end to
end: a real HTTP client (httpx) against the running gateway on simulated sensors, the
progress read from the procedure's own Server-Sent Events, the simulated sensor turned
as a person would turn it.  The rights are tried from the side of a client without
them."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from typing import Any

import httpx
import pytest
from support.harness import running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, SimulatorThread, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
TOKEN = "t0ken-for-procedure-tests"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
API = "/api/v1"
READING = Motion.from_seed(7).sample(4.0)


def config(path: str, protocol: str, series: str, **http: Any) -> dict[str, Any]:
    return {"gateway_id": "proc", "buses": [{
        "name": "line", "port": path, "baudrate": FAST, "protocol": protocol,
        "timeout_ms": 300, "sensors": [{"name": "boom", "series": series, "poll_hz": 20}]}],
        "http": {"listen": "127.0.0.1:0", "token": TOKEN, "allow_commands": True, **http}}


@asynccontextmanager
async def gateway_on(sensor: SimSensor, protocol: str, series: str, **http: Any,
                     ) -> AsyncIterator[tuple[Gateway, httpx.AsyncClient, SimulatorThread]]:
    with simulated([sensor]) as sim:
        async with running(config(sim.path, protocol, series, **http)) as gw:
            assert gw.http is not None
            await until(lambda: gw.cache.snapshot("boom").seq >= 1)
            async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{gw.http.port}",
                                         timeout=30) as http_client:
                yield gw, http_client, sim


async def events(http: httpx.AsyncClient, location: str) -> AsyncIterator[tuple[str, Any]]:
    """The procedure's events, (name, state), until ``end``."""
    async with http.stream("GET", f"{location}/events") as answer:
        assert answer.status_code == 200
        assert answer.headers["content-type"].startswith("text/event-stream")
        name = ""
        async for line in answer.aiter_lines():
            if line.startswith("event: "):
                name = line.removeprefix("event: ")
            elif line.startswith("data: "):
                yield name, json.loads(line.removeprefix("data: "))
                if name == "end":
                    return


async def start(http: httpx.AsyncClient, procedure: str, body: Any = None) -> str:
    answer = await http.post(f"{API}/sensors/boom/procedures/{procedure}", headers=AUTH,
                             json=body)
    assert answer.status_code == 201, answer.text
    assert answer.json()["state"] == "running"
    location = answer.headers["location"]
    assert location == f"{API}/sensors/boom/procedures/{procedure}/{answer.json()['id']}"
    return location


@pytest.mark.anyio
async def test_gyro_counts_down_calibrates_and_is_done() -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST, source=hold(READING))
    async with gateway_on(sensor, "native", "AH") as (_, http, _sim):
        location = await start(http, "gyro_calibration", {"countdown_s": 1.5})
        seen = [state async for _, state in events(http, location)]
        countdowns = [s["countdown_s"] for s in seen if s["step"] == "countdown"]
        assert countdowns and 0 < countdowns[0] <= 1.5  # the page can count down
        assert seen[0]["prompt"] == "Keep the sensor absolutely still"
        last = seen[-1]
        assert (last["state"], last["answers"]) == ("done", {"calibrate_gyro": {"code": 1}})
        assert last["elapsed_s"] >= 1.5
        assert sensor.writes_heard["calibrate_gyro"] == 1
        assert (await http.get(location)).json()["state"] == "done"


@pytest.mark.anyio
async def test_a_modbus_gyro_calibration_is_busy_until_the_sensor_says_done() -> None:
    sensor = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=FAST, source=hold(READING),
                         gyro_cal_duration=1.5)
    async with gateway_on(sensor, "modbus", "VG") as (gw, http, _sim):
        location = await start(http, "gyro_calibration", {"countdown_s": 0})
        seen = [state async for _, state in events(http, location)]
        assert "until_idle" in [s["step"] for s in seen]
        assert seen[-1]["state"] == "done" and seen[-1]["elapsed_s"] >= 1.4
        assert seen[-1]["answers"] == {"calibrate_gyro": {"value": 0}}  # 0: started
        assert not gw.cache.snapshot("boom").busy


@pytest.mark.anyio
async def test_mag_coverage_reaches_100_percent_as_the_sensor_is_turned() -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST)
    async with gateway_on(sensor, "native", "AH") as (_, http, sim):
        sim.call(sensor.lean, 0.0, 0.0).result(5)
        sim.call(sensor.turn, 0.0, 0.0, time.monotonic()).result(5)  # held still
        location = await start(http, "mag_calibration")
        coverage: list[float] = []
        async for _, state in events(http, location):
            coverage.append(state["coverage_percent"])
            if state["step"] == "circle" and sensor.turning is not None \
                    and sensor.turning.rate == 0.0:
                assert state["prompt"].startswith("Turn the sensor slowly through one full")
                sim.call(sensor.turn, 0.0, 90.0, time.monotonic()).result(5)  # 4 s a turn
            last = state
        assert 0 < min(c for c in coverage if c) < 100  # it grew as the sensor turned
        assert (last["state"], last["coverage_percent"], last["offers"]) == ("done", 100.0,
                                                                             ["save"])
        assert list(last["answers"]) == ["mag_calibration clear", "mag_calibration start",
                                         "mag_calibration finish"]
        assert last["quality"]["centre_offset_percent"] < 5  # the simulated field is round
        assert last["quality"]["ellipse_ratio"] < 1.05
        assert 30 <= len(last["points"]) <= 360
        heard = sensor.writes_heard
        assert (heard["clear_mag_calibration"], heard["start_mag_calibration"],
                heard["finish_mag_calibration"]) == (1, 1, 1)


@pytest.mark.anyio
async def test_zero_shows_the_angles_before_and_after() -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.VG, baud=FAST, source=hold(READING))
    async with gateway_on(sensor, "native", "VG") as (_, http, _sim):
        location = await start(http, "zero", {"type": "relative"})
        last = [state async for _, state in events(http, location)][-1]
        assert last["state"] == "done" and READING.angles is not None
        before, after = last["angles"]["before"], last["angles"]["after"]
        assert before["pitch"] == pytest.approx(READING.angles.pitch, abs=0.006)
        assert before["roll"] == pytest.approx(READING.angles.roll, abs=0.006)
        assert (after["pitch"], after["roll"]) == (0.0, 0.0)
        assert sensor.settings.zero_type == "relative"


@pytest.fixture
def held_ah() -> Iterator[SimSensor]:
    yield make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST, source=hold(READING))


@pytest.mark.anyio
async def test_cancel_clears_the_calibration_and_a_second_one_waits_for_it(
        held_ah: SimSensor) -> None:
    async with gateway_on(held_ah, "native", "AH") as (_, http, _sim):
        location = await start(http, "mag_calibration")
        second = await http.post(f"{API}/sensors/boom/procedures/gyro_calibration",
                                 headers=AUTH)
        assert second.status_code == 409 and second.json()["kind"] == "busy"
        assert second.json()["error"] == "boom is in mag_calibration 1: wait for it, or " \
            f"cancel it ({location})"
        await until(lambda: held_ah.writes_heard["start_mag_calibration"] == 1)
        cancelled = await http.delete(location, headers=AUTH)
        assert cancelled.status_code == 200 and cancelled.json()["state"] == "cancelled"
        await until(lambda: held_ah.writes_heard["clear_mag_calibration"] == 2)  # put back
        # (the sensor is the procedure's until the clear is answered: its events end then)
        async for _ in events(http, location):
            pass
        assert (await http.get(location)).json()["state"] == "cancelled"
        assert held_ah.writes_heard["finish_mag_calibration"] == 0
        await start(http, "zero", {"type": "absolute"})  # the sensor is free again


@pytest.mark.anyio
async def test_a_client_without_the_rights_cannot_start_or_cancel(held_ah: SimSensor) -> None:
    async with gateway_on(held_ah, "native", "AH") as (_, http, _sim):
        url = f"{API}/sensors/boom/procedures/gyro_calibration"
        nobody = await http.post(url)
        assert (nobody.status_code, nobody.json()["kind"]) == (401, "unauthorised")
        wrong = await http.post(url, headers={"Authorization": "Bearer guess"})
        assert wrong.status_code == 401
        location = await start(http, "gyro_calibration", {"countdown_s": 30})
        assert (await http.delete(location)).status_code == 401
        assert (await http.post(f"{location}/finish")).status_code == 401
        assert (await http.get(location)).json()["state"] == "running"  # reads are open
        big = await http.post(url, headers={**AUTH, "Content-Type": "application/json"},
                              content=b"[" * 20000)
        assert big.status_code == 413
        assert held_ah.writes_heard["calibrate_gyro"] == 0
    async with gateway_on(held_ah, "native", "AH", allow_commands=False) as (_, http, _sim):
        off = await http.post(url, headers=AUTH)
        assert (off.status_code, off.json()["kind"]) == (403, "forbidden")


@pytest.mark.anyio
async def test_what_the_sensor_cannot_do_is_refused_naming_why(held_ah: SimSensor) -> None:
    async with gateway_on(held_ah, "native", "AH") as (_, http, _sim):
        base = f"{API}/sensors/boom/procedures"
        listed = (await http.get(base)).json()
        assert listed["available"] == ["gyro_calibration", "mag_calibration", "zero",
                                       "change_address", "change_baudrate"]
        unknown = await http.post(f"{base}/spin", headers=AUTH)
        assert unknown.status_code == 404 and "known: gyro_calibration" in unknown.text
        heading = await http.post(f"{base}/zero", headers=AUTH,
                                  json={"type": "relative", "relative_heading": 10})
        assert heading.status_code == 422
        assert "zero needs set_relative_heading" in heading.json()["error"]
        bad = await http.post(f"{base}/zero", headers=AUTH, json={"type": "level"})
        assert bad.status_code == 422 and bad.json()["kind"] == "bad_arguments"
        nobody = await http.post(f"{API}/sensors/ghost/procedures/zero", headers=AUTH)
        assert nobody.status_code == 404
        assert (await http.get(f"{base}/zero/99")).status_code == 404


@pytest.mark.anyio
async def test_a_procedure_in_progress_ends_with_the_http_front_end(
        held_ah: SimSensor) -> None:
    """uvicorn runs without its lifespan events, so the front end's stop ends the
    procedures itself: none is left waiting for a circle nobody will turn."""
    async with gateway_on(held_ah, "native", "AH") as (gw, http, _sim):
        await start(http, "mag_calibration")
        await until(lambda: held_ah.writes_heard["start_mag_calibration"] == 1)
        left = [t for t in asyncio.all_tasks() if t.get_name().startswith("procedure ")]
        assert len(left) == 1 and not left[0].done()
        assert gw.http is not None
        await gw.http.stop()
        await until(lambda: left[0].done())
        assert left[0].cancelled() or left[0].exception() is None
