"""Scanning from the browser (docs/rest.md, "Scan"): ``POST /api/v1/scan`` finds a
sensor on a free port; on a port a bus of the gateway uses, it is refused until
confirmed, then that bus's polling pauses for the scan and resumes after it.

A real HTTP client (httpx) against the running gateway; the sensors are the
simulator's, behind real pseudo-terminals."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.harness import free_port, interrupt, running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimulatorThread, make_sensor, simulated

FAST = 115200
API = "/api/v1"
TOKEN = "t0ken-for-scan-tests"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def config(port: str) -> dict[str, Any]:
    return {"gateway_id": "scan", "http": {"listen": "127.0.0.1:0", "token": TOKEN},
            "buses": [{"name": "a", "port": port, "baudrate": FAST, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "poll_hz": 20}]}]}


def client(gateway: Gateway) -> httpx.AsyncClient:
    assert gateway.http is not None
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}", timeout=30)


async def events(http: httpx.AsyncClient, url: str) -> list[tuple[str, dict[str, Any]]]:
    """A scan's events, to its last."""
    out: list[tuple[str, dict[str, Any]]] = []
    name = ""
    async with http.stream("GET", url) as response:
        assert response.status_code == 200
        async for line in response.aiter_lines():
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                out.append((name, json.loads(line[6:])))
                if name in ("done", "failed", "cancelled"):
                    break
    return out


@pytest.mark.anyio
async def test_a_scan_of_a_free_port_finds_the_sensor() -> None:
    target = make_sensor(WireProtocol.NATIVE, Series.AH, 7, baud=19200)
    polled = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([target]) as free, simulated([polled]) as used:
        async with running(config(used.path)) as gateway, client(gateway) as http:
            body = {"port": free.path, "protocols": ["native"], "bauds": [9600, 19200],
                    "first_address": 5, "last_address": 9}
            refused = await http.post(f"{API}/scan", json=body)  # no token: admin's only
            assert refused.status_code == 401
            bad = await http.post(f"{API}/scan", json={**body, "bauds": [1234]}, headers=AUTH)
            assert bad.status_code == 422 and "1234" in bad.json()["error"]
            started = await http.post(f"{API}/scan", json=body, headers=AUTH)
            assert started.status_code == 202, started.text
            job = started.json()
            assert job["paused_bus"] is None and job["estimate_s"] > 0
            got = await events(http, job["events"])
            after = (await http.get(f"{API}/scan/{job['id']}")).json()
            listed = (await http.get(f"{API}/scan")).json()
    names = [name for name, _ in got]
    assert names[0] == "progress" and names[-1] == "done"
    assert "seconds_left" in got[0][1] and "9600 baud" in got[0][1]["text"]
    found = [data for name, data in got if name == "found"]
    assert found == [{"protocol": "native", "baudrate": 19200, "address": 7, "series": "AH"}]
    assert after["finished"] and after["found"] == found
    assert listed == [after]


@pytest.mark.anyio
async def test_a_scan_of_a_line_in_use_pauses_its_polling_and_resumes_it() -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([sensor]) as sim:
        async with running(config(sim.path)) as gateway, client(gateway) as http:
            await until(lambda: gateway.cache.snapshot("boom").seq >= 5)
            body = {"port": sim.path, "protocols": ["native"], "bauds": [FAST]}
            asked = await http.post(f"{API}/scan", json=body, headers=AUTH)
            # Said before anything stops: whose port it is, and what confirming does.
            assert asked.status_code == 409, asked.text
            said = asked.json()["error"]
            assert "bus a's port" in said and "pauses" in said and '"confirm": true' in said
            assert gateway.stats()[0].port_open
            started = await http.post(f"{API}/scan", json={**body, "confirm": True},
                                      headers=AUTH)
            assert started.status_code == 202, started.text
            assert started.json()["paused_bus"] == "a"
            got = await events(http, started.json()["events"])
            seq = gateway.cache.snapshot("boom").seq
            # Readings go on after the scan.
            await until(lambda: gateway.cache.snapshot("boom").seq >= seq + 5)
            assert gateway.stats()[0].port_open
    found = [data for name, data in got if name == "found"]
    assert found == [{"protocol": "native", "baudrate": FAST, "address": 0, "series": "AH"}]
    assert got[-1][0] == "done"
    assert sim.bus.stats.masters_overlaps == 0  # the scan and the bus never both wrote



@pytest.mark.anyio
async def test_a_scan_waits_out_the_answer_the_paused_bus_was_still_owed() -> None:
    """A slow sensor polled flat out: when the scan is asked for, the bus has a request
    in flight and its answer is 30-40 ms away.  The scan's first request goes only
    after it (else it meets the answer on the wire, and the answer, heard by the scan,
    looks like another sensor's stream frame)."""
    async with slow_line(answer_delay=0.03, jitter=0.01) as (sim, gateway, http):
        for _ in range(3):
            await polled_again(gateway)
            got = await scan_paused_line(http, sim.path, 255)
            found = [data for name, data in got if name == "found"]
            assert found == [{"protocol": "native", "baudrate": FAST, "address": 0,
                              "series": "AH"}], got
            assert sim.bus.stats.masters_overlaps == 0, incidents(sim)


@pytest.mark.anyio
async def test_the_bus_resumes_once_the_scans_last_request_can_no_longer_be_answered(
        ) -> None:
    """A sensor slower than the scan's margin (150 ms against 100): the scan hears no
    answer to its query and ends, but the sensor answers all the same.  The bus's
    first poll after the scan must not meet that answer."""
    async with slow_line(answer_delay=0.15) as (sim, gateway, http):
        for _ in range(2):
            await polled_again(gateway)
            got = await scan_paused_line(http, sim.path, 255)
            assert [name for name, _ in got if name != "progress"] == ["done"], got
            await polled_again(gateway)
            assert sim.bus.stats.masters_overlaps == 0, incidents(sim)


@contextlib.asynccontextmanager
async def slow_line(**timing: float) -> AsyncIterator[
        tuple[SimulatorThread, Gateway, httpx.AsyncClient]]:
    """Bus a with one slow AH (the simulator's ``answer_delay``, ``jitter``), polled
    flat out (a request always in flight) with a learned timeout (the bus's own hold
    after a request): its simulator, the gateway and a client of its REST."""
    slow = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST, **timing)
    cfg = config("")
    cfg["buses"][0]["sensors"][0]["poll_hz"] = 0
    del cfg["buses"][0]["timeout_ms"]
    with simulated([slow]) as sim:
        cfg["buses"][0]["port"] = sim.path
        async with running(cfg) as gateway, client(gateway) as http:
            yield sim, gateway, http


def incidents(sim: SimulatorThread) -> str:
    """The simulator's first overlaps and collisions, with what led to each."""
    return "\n".join("\n".join(events) for events in sim.bus.stats.incidents)


async def polled_again(gateway: Gateway) -> None:
    """Until the bus has taken three more readings (it polls again)."""
    seq = gateway.cache.snapshot("boom").seq
    await until(lambda: gateway.cache.snapshot("boom").seq >= seq + 3)


@pytest.mark.anyio
async def test_a_scan_can_be_cancelled_and_a_missing_port_is_said() -> None:
    polled = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([]) as empty, simulated([polled]) as used:
        async with running(config(used.path)) as gateway, client(gateway) as http:
            missing = await http.post(f"{API}/scan", json={"port": "/dev/does-not-exist"},
                                      headers=AUTH)
            got = await events(http, missing.json()["events"])
            assert got[-1][0] == "failed" and "/dev/does-not-exist" in got[-1][1]["error"]
            # every Modbus unit at every rate: minutes, cancelled at once
            long = await http.post(f"{API}/scan", json={"port": empty.path,
                                                        "protocols": ["modbus"]},
                                   headers=AUTH)
            assert long.json()["estimate_s"] > 60
            scan_id = long.json()["id"]
            again = await http.post(f"{API}/scan", json={"port": empty.path}, headers=AUTH)
            assert again.status_code == 409 and "under way" in again.json()["error"]
            assert (await http.post(f"{API}/scan/{scan_id}/cancel")).status_code == 401
            cancelled = await http.post(f"{API}/scan/{scan_id}/cancel", headers=AUTH)
            assert cancelled.status_code == 200, cancelled.text
            got = await events(http, long.json()["events"])
            assert (await http.get(f"{API}/scan/nope")).status_code == 404
    assert got[-1][0] == "cancelled"


def test_a_scan_under_way_does_not_hold_the_gateways_stop(tmp_path: Path) -> None:
    """SIGINT during a scan of minutes: the scan ends at its next address and the
    process exits 0 (the stop's own grace, not the scan's length)."""
    polled = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    with simulated([]) as empty, simulated([polled]) as used:
        cfg = config(used.path)
        port = free_port()
        cfg["http"]["listen"] = f"127.0.0.1:{port}"
        path = tmp_path / "gateway.yaml"
        path.write_text(json.dumps(cfg))  # (JSON is YAML)
        base = f"http://127.0.0.1:{port}"
        with (tmp_path / "gateway.log").open("wb") as log:
            process = subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c",
                                        str(path)], stdout=log, stderr=subprocess.STDOUT)
        try:
            started = None
            deadline = time.monotonic() + 30
            while started is None and time.monotonic() < deadline:
                with contextlib.suppress(httpx.TransportError):
                    started = httpx.post(f"{base}{API}/scan", headers=AUTH, timeout=5,
                                         json={"port": empty.path, "protocols": ["modbus"]})
                time.sleep(0.05)
            assert started is not None and started.status_code == 202
            assert started.json()["estimate_s"] > 60
            with httpx.stream("GET", f"{base}{started.json()['events']}", timeout=10) as r:
                next(line for line in r.iter_lines() if line == "event: progress")
        finally:
            code = interrupt(process, timeout=15)
    assert code == 0, (tmp_path / "gateway.log").read_text()[-2000:]
    assert "Traceback" not in (tmp_path / "gateway.log").read_text()


def streaming_config(port: str) -> dict[str, Any]:
    """Bus a with one sensor, boom at address 2, streaming 50 frames a second."""
    cfg = config(port)
    cfg["buses"][0]["sensors"] = [{"name": "boom", "series": "AH", "address": 2,
                                   "stream_hz": 50}]
    return cfg


async def scan_paused_line(http: httpx.AsyncClient, port: str,
                           last: int) -> list[tuple[str, dict[str, Any]]]:
    body = {"port": port, "protocols": ["native"], "bauds": [FAST], "first_address": 0,
            "last_address": last, "confirm": True}
    started = await http.post(f"{API}/scan", json=body, headers=AUTH)
    assert started.status_code == 202, started.text
    assert started.json()["paused_bus"] == "a"
    return await events(http, started.json()["events"])


@pytest.mark.anyio
async def test_a_streaming_sensor_alone_is_found_by_the_address_query() -> None:
    """Its stream frames are neither answers nor a collision: the one answer to the
    address query finds it, with no address asked one by one."""
    streamer = make_sensor(WireProtocol.NATIVE, Series.AH, 2, baud=FAST)
    with simulated([streamer]) as sim:
        async with running(streaming_config(sim.path)) as gateway, client(gateway) as http:
            await until(lambda: gateway.cache.snapshot("boom").seq >= 20)  # streaming
            got = await scan_paused_line(http, sim.path, 255)
            streamed = streamer.stream_interval  # (the gateway's stop ends it)
            seq = gateway.cache.snapshot("boom").seq
            await until(lambda: gateway.cache.snapshot("boom").seq >= seq + 5)
    assert streamed == 1 / 50  # it streamed all along
    found = [data for name, data in got if name == "found"]
    assert found == [{"protocol": "native", "baudrate": FAST, "address": 2, "series": "AH"}]
    one_by_one = [data["text"] for name, data in got
                  if name == "progress" and data["address"] is not None]
    assert one_by_one == []
    assert got[-1][0] == "done"


@pytest.mark.anyio
async def test_a_scan_beside_a_streaming_sensor_finds_every_sensor() -> None:
    """A quiet sensor on the line of a streaming one: the stream's frames do not end
    the wait for the quiet one's answer, and the requests go between them."""
    streamer = make_sensor(WireProtocol.NATIVE, Series.AH, 2, baud=FAST)
    quiet = [make_sensor(WireProtocol.NATIVE, series, address, baud=FAST)
             for series, address in ((Series.VG, 5), (Series.IMU, 9), (Series.AH, 12),
                                     (Series.VG, 14))]
    with simulated([streamer, *quiet]) as sim:
        async with running(streaming_config(sim.path)) as gateway, client(gateway) as http:
            await until(lambda: gateway.cache.snapshot("boom").seq >= 20)
            got = await scan_paused_line(http, sim.path, 15)
            streamed = streamer.stream_interval
    assert streamed == 1 / 50
    found = [(data["address"], data["series"]) for name, data in got if name == "found"]
    assert found == [(2, "AH"), (5, "VG or MINS"), (9, "IMU"), (12, "AH"), (14, "VG or MINS")]
    assert got[-1][0] == "done"
