"""The live traffic monitor (docs/rest.md, "Traffic"): ``GET /api/v1/buses/{bus}/traffic``
shows the real frames of a simulated line, at most 50 a second per client (the rest
counted and said), and the bus makes no trace at all while nobody watches.

A real HTTP client (httpx) against the running gateway on simulated sensors."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack
from datetime import datetime
from typing import Any

import httpx
import pytest
from support.harness import running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

FAST = 115200
API = "/api/v1"


def config(port: str, poll_hz: float, sensors: int = 1) -> dict[str, Any]:
    return {"gateway_id": "traffic", "http": {"listen": "127.0.0.1:0"},
            "buses": [{"name": "a", "port": port, "baudrate": FAST, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": f"s{i}", "series": "AH", "address": i,
                                    "poll_hz": poll_hz} for i in range(sensors)]}]}


def client(gateway: Gateway) -> httpx.AsyncClient:
    assert gateway.http is not None
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}", timeout=10)


async def sse(response: httpx.Response) -> AsyncIterator[tuple[str, dict[str, Any]]]:
    """The stream's events, as (name, data)."""
    name = ""
    async for line in response.aiter_lines():
        if line.startswith("event: "):
            name = line[7:]
        elif line.startswith("data: "):
            yield name, json.loads(line[6:])


def traced(gateway: Gateway) -> int:
    return gateway.masters["a"].schedule.outcomes.traced


@pytest.mark.anyio
async def test_traffic_shows_the_lines_frames_and_nothing_is_traced_unwatched() -> None:
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)]) as sim:
        async with running(config(sim.path, 20)) as gateway, client(gateway) as http:
            # Nobody watches: the bus polls and makes no trace.
            await until(lambda: gateway.cache.snapshot("s0").seq >= 10)
            assert traced(gateway) == 0
            frames = []
            async with http.stream("GET", f"{API}/buses/a/traffic") as response:
                assert response.status_code == 200
                async for name, data in sse(response):
                    if name == "frame":
                        frames.append(data)
                    if len(frames) == 5:
                        break
            assert traced(gateway) >= 5
            # The last watcher gone, the bus stops tracing: its count stands still
            # while the polls go on.
            await until(lambda: not gateway.masters["a"].schedule.outcomes.tracing)
            count, seq = traced(gateway), gateway.cache.snapshot("s0").seq
            await until(lambda: gateway.cache.snapshot("s0").seq >= seq + 10)
            assert traced(gateway) == count
            unknown = await http.get(f"{API}/buses/nope/traffic")
    assert unknown.status_code == 404 and "the buses: a" in unknown.json()["error"]
    for frame in frames:
        assert frame["sensor"] == "s0" and frame["outcome"] == "ok" and not frame["error"]
        assert frame["tx"] == "77 04 00 59 5D"  # the combined read of address 0
        assert frame["rx"].startswith("77 ") and frame["took_ms"] > 0
        assert frame["time"].endswith("Z")


@pytest.mark.anyio
async def test_traffic_sends_at_most_50_frames_a_second_and_counts_the_rest() -> None:
    sensors = [make_sensor(WireProtocol.NATIVE, Series.AH, i, baud=FAST) for i in range(4)]
    with simulated(sensors) as sim:
        # 4 sensors at 50 Hz: about 200 exchanges a second, if the line carries them
        async with running(config(sim.path, 50, 4)) as gateway, client(gateway) as http:
            frames: list[dict[str, Any]] = []
            skipped: list[int] = []
            async with http.stream("GET", f"{API}/buses/a/traffic") as response:
                async for name, data in sse(response):
                    if name == "frame":
                        frames.append(data)
                    elif name == "skipped":
                        skipped.append(data["skipped"])
                        assert data["limit_per_s"] == 50
                    if len(skipped) >= 3:
                        break
            assert traced(gateway) > len(frames)
    assert sum(skipped) > 0
    # Each second counted from the first frame shown in it (the frames' own times, to
    # the ms, so a frame 2 ms before a second's end may open the next): at most 50.
    times = [datetime.fromisoformat(f["time"]).timestamp() for f in frames]
    start, shown, most = -1.0, 0, 0
    for t in times:
        if t - start >= 0.998:
            start, shown = t, 0
        shown += 1
        most = max(most, shown)
    assert most <= 50 and len(frames) >= 100


@pytest.mark.anyio
async def test_traffic_filters_by_sensor_and_errors() -> None:
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)]) as sim:
        body = config(sim.path, 20, 2)  # s1 (address 1) is not there: timeouts
        async with running(body) as gateway, client(gateway) as http:
            got: list[dict[str, Any]] = []
            async with http.stream("GET", f"{API}/buses/a/traffic",
                                   params={"errors": "true"}) as response:
                async for name, data in sse(response):
                    if name == "frame":
                        got.append(data)
                    if len(got) == 2:
                        break
            ok: list[dict[str, Any]] = []
            async with http.stream("GET", f"{API}/buses/a/traffic",
                                   params={"sensor": "s0"}) as response:
                async for name, data in sse(response):
                    if name == "frame":
                        ok.append(data)
                    if len(ok) == 3:
                        break
            assert traced(gateway) > 0
    assert all(f["sensor"] == "s1" and f["error"] and "timeout" in f["outcome"] for f in got)
    assert all(f["rx"] == "" for f in got)
    assert all(f["sensor"] == "s0" for f in ok)


async def _open_monitor(stack: AsyncExitStack, http: httpx.AsyncClient) -> httpx.Response:
    """A traffic monitor held open (its headers in) until ``stack`` closes."""
    return await stack.enter_async_context(http.stream("GET", f"{API}/buses/a/traffic"))


@pytest.mark.anyio
async def test_at_most_16_traffic_monitors_from_one_address_and_others_still_get_in() -> None:
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)]) as sim:
        async with running(config(sim.path, 20)) as gateway, AsyncExitStack() as stack:
            assert gateway.http is not None
            base = f"http://127.0.0.1:{gateway.http.port}"
            # The one trying to take every place: 17 monitors from one address, each
            # on its own connection, all held open.
            attacker = await stack.enter_async_context(httpx.AsyncClient(
                base_url=base, timeout=10, limits=httpx.Limits(max_connections=40)))
            held = [await _open_monitor(stack, attacker) for _ in range(16)]
            assert [r.status_code for r in held] == [200] * 16
            refused = await attacker.get(f"{API}/buses/a/traffic")
            # Another address (the loopback's 127.0.0.2) still gets in.
            other = await stack.enter_async_context(httpx.AsyncClient(
                base_url=base, timeout=10,
                transport=httpx.AsyncHTTPTransport(local_address="127.0.0.2")))
            async with other.stream("GET", f"{API}/buses/a/traffic") as response:
                assert response.status_code == 200
                async for name, _ in sse(response):
                    if name == "frame":
                        break
            # One of the 16 closed, its place is the attacker's again.
            await held[0].aclose()
            again = None

            async def one_more() -> bool:
                nonlocal again
                response = await attacker.send(attacker.build_request(
                    "GET", f"{API}/buses/a/traffic"), stream=True)
                if response.status_code == 429:
                    await response.aclose()
                    return False
                again = response
                return True
            await until(one_more)
            assert again is not None and again.status_code == 200
            await again.aclose()
    assert refused.status_code == 429
    assert refused.json()["kind"] == "too_many_watchers"
    assert refused.json()["error"] == ("16 traffic monitors are open from 127.0.0.1 "
                                       "already: close one (a page or tab showing the "
                                       "traffic) and try again")
