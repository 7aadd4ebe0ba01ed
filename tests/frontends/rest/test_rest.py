"""The REST API, live stream and metrics (docs/rest.md, issue 6) through a real HTTP
client (httpx) against the running gateway on simulated sensors.

Expected values come from the simulator, the config and docs/rest.md.  Waits are
deadlines on conditions, never measurements of speed.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import json
import math
import re
import shutil
import socket
import subprocess
from collections.abc import AsyncIterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from support import ROOT
from support.derived import EXACT, exact_tilt
from support.harness import expected, fields_of, running, tolerance, until

from imu_gateway import __version__
from imu_gateway.app import Gateway, openapi_json
from imu_gateway.config import SensorConfig
from imu_gateway.errors import StartupError
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, SimSensor, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion
from imu_gateway.stats import ERROR_KINDS

FAST = 115200
READING = Motion.from_seed(3).sample(10.0)
TOKEN = "t0ken-for-tests"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
API = "/api/v1"


def sensor(protocol: WireProtocol, series: Series, **options: Any) -> SimSensor:
    return make_sensor(protocol, series, baud=FAST, **options)


def bus(name: str, port: str, protocol: str, sensors: list[dict[str, Any]]) -> dict[str, Any]:
    return {"name": name, "port": port, "baudrate": FAST, "protocol": protocol,
            "timeout_ms": 300, "sensors": sensors}


def config(buses: list[dict[str, Any]], **http: Any) -> dict[str, Any]:
    return {"gateway_id": "test", "buses": buses,
            "http": {"listen": "127.0.0.1:0", "token": TOKEN, "allow_commands": True, **http}}


def client(gateway: Gateway) -> httpx.AsyncClient:
    assert gateway.http is not None
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}", timeout=10)




def assert_error(response: httpx.Response, status: int, kind: str) -> None:
    assert response.status_code == status, response.text
    body = response.json()
    assert body["kind"] == kind and body["error"], body


@pytest.fixture
def two_lines() -> Any:
    """A native AH and a Modbus VG, each on its own line."""
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING), save_duration=1.0)
    vg = sensor(WireProtocol.MODBUS, Series.VG, address=1, source=hold(READING))
    with simulated([ah]) as line_a, simulated([vg]) as line_b:
        yield ah, vg, [bus("a", line_a.path, "native", [{"name": "boom", "series": "AH"}]),
                       bus("b", line_b.path, "modbus", [{"name": "arm", "series": "VG"}])]


# ------------------------------------------------------------------ reads


def test_history_keeps_each_seconds_lowest_highest_and_last() -> None:
    """A pure check of the ring: buckets by the sample's own second, NaN is no value,
    a step back of the clock is ignored, and a query takes the last N seconds."""
    from imu_gateway.history import KEEP_S, History

    gateway = SimpleNamespace(sensors={"s": SensorConfig(name="s", series=Series.IMU,
                                                          address=0)})
    history = History(gateway)
    n = len(history.fields["s"])  # an IMU: accel and gyro, 6 fields, and the vibration
    assert n == 7
    for at, v in ((100.1, 1.0), (100.5, -2.0), (100.9, 0.5), (101.2, math.nan),
                  (99.0, 7.0), (102.0, 3.0)):
        history.add("s", at, [v] * n)
    got = history.query("s", 10, now=102.5)
    assert got["t"] == [100, 101, 102]
    accel_x = got["fields"]["accel_x"]
    assert accel_x == {"min": [-2.0, None, 3.0], "max": [1.0, None, 3.0],
                       "last": [0.5, None, 3.0]}
    # the buckets that overlap the last second
    assert history.query("s", 1, now=102.5)["t"] == [101, 102]
    for second in range(KEEP_S + 50):  # a ring: the oldest go
        history.add("s", 200.0 + second, [1.0] * n)
    assert len(history.query("s", KEEP_S, now=200.0 + KEEP_S + 50)["t"]) <= KEEP_S



@pytest.mark.anyio
async def test_the_api_reference_and_index_are_served_from_the_gateway(two_lines: Any) -> None:
    """/docs is Swagger UI with every file from this server (no CDN: plant networks
    have no internet); /api/v1 lists the endpoints and points at both."""
    _, _, buses = two_lines
    async with running(config(buses)) as gateway, client(gateway) as http:
        docs = await http.get("/docs")
        assert docs.status_code == 200 and "text/html" in docs.headers["content-type"]
        assets = re.findall(r'(?:src|href)="([^"]+)"', docs.text)
        assert assets and all(a.startswith("/") for a in assets), assets  # nothing remote
        for asset in assets:
            fetched = await http.get(asset)
            assert fetched.status_code == 200 and fetched.content, asset
        index = (await http.get(API)).json()
        assert index["docs"] == "/docs" and index["version"] == __version__
        endpoints = {(e["method"], e["path"]) for e in index["endpoints"]}
        assert ("GET", f"{API}/health") in endpoints
        assert ("POST", f"{API}/sensors/{{name}}/commands/save") in endpoints
        assert (await http.get(index["openapi"])).json()["info"]["title"] == "imu-gateway"
        dashboard = (await http.get("/")).text
        assert 'href="docs"' in dashboard


@pytest.mark.anyio
async def test_every_answer_keeps_the_browser_to_the_gateway(two_lines: Any) -> None:
    """The headers docs/rest.md lists ("Headers"): no sniffing and no Referer on every
    answer; no-store on all but the static files; a policy that lets the pages load
    only the gateway's own files (the docs page's one inline script by its hash), and
    data nothing at all."""
    _, _, buses = two_lines
    async with running(config(buses)) as gateway, client(gateway) as http:
        await until(lambda: gateway.cache.snapshot("boom").seq >= 1)
        answers = {path: await http.get(path) for path in (
            "/", "/docs", f"{API}/health", f"{API}/sensors/boom/reading", "/metrics",
            "/openapi.json", f"{API}/nowhere", "/static/dashboard.js",
            "/docs/assets/swagger-ui.css")}
        answers["401"] = await http.post(f"{API}/sensors/boom/commands/save")
        async with http.stream("GET", f"{API}/stream") as stream:
            answers["stream"] = stream
        for what, answer in answers.items():
            headers = answer.headers
            assert headers["x-content-type-options"] == "nosniff", what
            assert headers["referrer-policy"] == "no-referrer", what
            cached = what.startswith(("/static/", "/docs/assets/"))
            assert headers.get("cache-control") == (None if cached else "no-store"), what
            policy = headers["content-security-policy"]
            assert "frame-ancestors 'none'" in policy, what
            if what in ("/", "/docs"):
                assert "default-src 'self'" in policy and "unsafe" not in policy, what
            else:
                assert "default-src 'none'" in policy, what
        docs_policy = answers["/docs"].headers["content-security-policy"]
        script = re.search(r"<script>(.*?)</script>", answers["/docs"].text, re.S)
        assert script is not None
        digest = base64.b64encode(hashlib.sha256(script.group(1).encode()).digest()).decode()
        assert f"'sha256-{digest}'" in docs_policy


@pytest.mark.anyio
async def test_health_buses_sensors_and_readings(two_lines: Any) -> None:
    ah, vg, buses = two_lines

    async with running(config(buses)) as gateway, client(gateway) as http:
        await until(lambda: all(s.seq >= 2 for s in gateway.cache.snapshots()))
        # the counters come as the bus publishes them (at most STATS_EVERY old)
        await until(lambda: all(b.transactions >= 2 for b in gateway.stats()))
        health = (await http.get(f"{API}/health")).json()
        assert health["status"] == "ok" and health["gateway_id"] == "test"
        assert health["version"] == __version__
        assert health["buses"] == {"a": True, "b": True}
        assert health["sensors"] == {"ok": 2, "stale": 0, "offline": 0}
        assert health["interfaces"] == ["http"]
        # counters are whole numbers ("clients": 1, never 1.0), connected stays true/false
        counters = [v for front in health["frontends"].values() for v in front.values()]
        assert counters and all(type(v) is int for v in counters)

        # the recent past, a bucket a second
        history = (await http.get(f"{API}/sensors/boom/history", params={"seconds": 60}))
        assert history.status_code == 200
        past = history.json()
        # an AH measures 16 fields; 3 more are derived from them
        assert past["t"] and len(past["fields"]) == 19
        assert {"tilt", "tilt_direction", "vibration"} <= set(past["fields"])
        pitch = past["fields"]["pitch"]
        assert all(lo <= last <= hi for lo, last, hi in
                   zip(pitch["min"], pitch["last"], pitch["max"], strict=True))
        assert_error(await http.get(f"{API}/sensors/boom/history",
                                    params={"seconds": 10_000}), 422, "bad_arguments")
        assert_error(await http.get(f"{API}/sensors/nobody/history"), 404, "unknown_sensor")

        # the value groups and their units, from the gateway's one table (the
        # dashboard labels its values with these)
        groups = {g["group"]: g for g in (await http.get(f"{API}/groups")).json()}
        assert list(groups) == ["angles", "accel", "gyro", "mag", "quaternion", "tilt",
                                "vibration"]
        assert groups["gyro"] == {"group": "gyro", "fields": ["gyro_x", "gyro_y", "gyro_z"],
                                  "members": ["x", "y", "z"], "unit": "°/s",
                                  "unit_name": "degrees per second", "digits": 2,
                                  "derived_from": []}
        assert groups["tilt"] == {"group": "tilt", "fields": ["tilt", "tilt_direction"],
                                  "members": ["tilt", "tilt_direction"], "unit": "°",
                                  "unit_name": "degrees", "digits": 2,
                                  "derived_from": ["angles"]}
        assert groups["vibration"]["derived_from"] == ["accel"]
        assert groups["vibration"]["unit"] == "g" and groups["vibration"]["digits"] == 4

        buses_out = {b["name"]: b for b in (await http.get(f"{API}/buses")).json()}
        assert buses_out["a"]["protocol"] == "native" and buses_out["b"]["protocol"] == "modbus"
        assert buses_out["a"]["baudrate"] == FAST and buses_out["a"]["sensors"] == ["boom"]
        assert buses_out["a"]["transactions"] >= 2 and buses_out["a"]["port_open"] is True
        assert 0 < buses_out["a"]["utilisation"] <= 1.0
        assert buses_out["a"]["late_writes"] == 0  # (no stream on the line: no place)
        # each sensor's learned answer timing: never less than the simulator's delay
        timing = buses_out["a"]["timing"]["boom"]
        assert timing["latency_ms"] >= 0.9 * ah.answer_delay * 1000
        assert timing["timeout_ms"] >= timing["latency_ms"]
        assert set(buses_out["b"]["timing"]) == {"arm"}
        # the configured rate beside the one achieved (poll_hz of the config below)
        assert timing["requested_hz"] == gateway.sensors["boom"].poll_hz
        assert timing["achieved_hz"] > 0

        listed = {s["name"]: s for s in (await http.get(f"{API}/sensors")).json()}
        assert listed["boom"]["series"] == "AH" and listed["arm"]["protocol"] == "modbus"
        assert listed["boom"]["status"] == "ok" and listed["boom"]["unit_id"] == 1

        detail = (await http.get(f"{API}/sensors/arm")).json()
        assert detail["config"]["address"] == 1 and detail["reading"]["sensor"] == "arm"
        # a VG measures no magnetic field: the group is absent, never null, in the
        # detail's reading as in the reading itself
        assert set(detail["reading"]) == {"sensor", "ts", "seq", "status", "angles",
                                          "accel", "gyro", "quaternion", "tilt", "vibration"}
        assert "age_ms" in detail and "settings" in detail  # the route's own fields

        for name, sim, protocol in (("boom", ah, WireProtocol.NATIVE),
                                    ("arm", vg, WireProtocol.MODBUS)):
            response = await http.get(f"{API}/sensors/{name}/reading")
            assert response.status_code == 200
            got = response.json()
            assert got["status"] == "ok" and got["seq"] >= 2
            want = expected(sim)
            assert set(fields_of(got)) == set(want)  # a VG has no "mag" group
            for field_name, value in fields_of(got).items():
                assert abs(value - want[field_name]) <= tolerance(
                    protocol, field_name, value), (name, field_name)

        assert_error(await http.get(f"{API}/sensors/nobody"), 404, "unknown_sensor")
        assert_error(await http.get(f"{API}/sensors/nobody/reading"), 404, "unknown_sensor")
        assert_error(await http.get(f"{API}/nothing/here"), 404, "not_found")



@pytest.mark.anyio
async def test_max_age_reads_the_bus_and_a_silent_sensor_is_504(two_lines: Any) -> None:
    ah, _, buses = two_lines
    buses[0]["sensors"][0]["poll_hz"] = 0.2  # a reading every 5 s: max_age must ask

    async with running(config(buses)) as gateway, client(gateway) as http:
        await until(lambda: gateway.cache.snapshot("boom").seq >= 1)
        await asyncio.sleep(0.3)
        before = gateway.cache.snapshot("boom").seq
        fresh = (await http.get(f"{API}/sensors/boom/reading",
                                params={"max_age_ms": 100})).json()
        assert fresh["seq"] > before  # read from the bus, not the cache
        cached = (await http.get(f"{API}/sensors/boom/reading",
                                 params={"max_age_ms": 60_000})).json()
        assert cached["seq"] == fresh["seq"]  # young enough: no bus read
        assert_error(await http.get(f"{API}/sensors/boom/reading",
                                    params={"max_age_ms": -1}), 422, "bad_arguments")
        assert_error(await http.get(f"{API}/sensors/boom/reading",
                                    params={"max_age_ms": "soon"}), 422, "bad_arguments")
        ah.faults.stalled = True
        response = await http.get(f"{API}/sensors/boom/reading", params={"max_age_ms": 0})
        assert response.status_code == 504, response.text
        # without max_age_ms the cached reading is served, marked for what it is
        await until(lambda: gateway.cache.snapshot("boom").status.value == "offline",
                    timeout=20)
        old = (await http.get(f"{API}/sensors/boom/reading")).json()
        assert old["status"] == "offline" and old["seq"] == fresh["seq"]
        assert (await http.get(f"{API}/health")).json()["status"] == "degraded"



@pytest.mark.anyio
async def test_no_reading_yet_is_503(tmp_path: Path) -> None:
    dead = sensor(WireProtocol.NATIVE, Series.AH, faults=Faults(stalled=True))
    with simulated([dead]) as line:
        buses = [bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])]

        async with running(config(buses)) as gateway, client(gateway) as http:
            assert_error(await http.get(f"{API}/sensors/boom/reading"), 503, "no_reading")
            detail = (await http.get(f"{API}/sensors/boom")).json()
            assert detail["reading"] is None and detail["status"] == "offline"



@pytest.mark.anyio
async def test_read_token_required(two_lines: Any) -> None:
    _, _, buses = two_lines

    async with running(config(buses, read_token_required=True)) as gateway, \
            client(gateway) as http:
        for path in ("/health", "/buses", "/sensors", "/sensors/boom"):
            response = await http.get(API + path)
            assert_error(response, 401, "unauthorised")
            assert response.headers["WWW-Authenticate"] == "Bearer"
            assert (await http.get(API + path, headers=AUTH)).status_code == 200
        assert (await http.get("/metrics")).status_code == 401
        # No token in a URL: ?access_token= is not a credential, on a stream neither
        # (a URL lands in logs and histories); the header is.
        assert_error(await http.get(f"{API}/stream", params={"access_token": TOKEN}),
                     401, "unauthorised")
        async with http.stream("GET", f"{API}/sensors/boom/stream",
                               headers=AUTH) as response:
            assert response.status_code == 200
            async for name, _ in sse_events(response):
                assert name in ("reading", "status")
                break
        wrong = {"Authorization": "Bearer not-it"}
        assert_error(await http.get(f"{API}/health", headers=wrong), 401, "unauthorised")



# ------------------------------------------------------------------ commands


@pytest.mark.anyio
async def test_commands_status_codes(two_lines: Any) -> None:
    ah, vg, buses = two_lines

    async def post(http: httpx.AsyncClient, path: str, body: Any = None, *,
                   headers: dict[str, str] | None = AUTH, **options: Any) -> httpx.Response:
        return await http.post(f"{API}/sensors/{path}", json=body, headers=headers, **options)

    async with running(config(buses)) as gateway, client(gateway) as http:
        await until(lambda: all(s.seq >= 1 for s in gateway.cache.snapshots()))
        response = await post(http, "boom/commands/set_zero_type", {"type": "relative"})
        assert response.status_code == 200, response.text
        assert response.json()["ok"] is True and ah.settings.zero_type == "relative"
        settings = (await post(http, "boom/commands/read_settings")).json()
        assert settings["answer"]["zero_type"] == "relative"
        assert (await http.get(f"{API}/sensors/boom")).json()["settings"]["zero_type"] \
            == "relative"

        # auth
        response = await post(http, "boom/commands/save", headers=None)
        assert_error(response, 401, "unauthorised")
        assert response.headers["WWW-Authenticate"] == "Bearer"
        assert_error(await post(http, "boom/commands/save",
                                headers={"Authorization": "Bearer nope"}),
                     401, "unauthorised")
        assert_error(await post(http, "boom/commands/save",
                                headers={"Authorization": "Basic dXNlcjpwdw=="}),
                     401, "unauthorised")
        # bad arguments, each with its reason
        bad = await post(http, "boom/commands/set_zero_type", {"type": "sideways"})
        assert_error(bad, 422, "bad_arguments")
        assert "type" in bad.json()["error"]
        assert_error(await post(http, "boom/commands/set_zero_type", {"type": "absolute",
                                                                      "extra": 1}),
                     422, "bad_arguments")
        assert_error(await post(http, "boom/commands/set_zero_type"), 422, "bad_arguments")
        assert_error(await post(http, "boom/commands/set_declination", {"degrees": 200}),
                     422, "bad_arguments")
        assert_error(await post(http, "boom/commands/save", {"now": True}),
                     422, "bad_arguments")
        raw = await http.post(f"{API}/sensors/boom/commands/set_zero_type",
                              content=b"{not json", headers={
                                  **AUTH, "Content-Type": "application/json"})
        assert_error(raw, 422, "bad_arguments")
        # JSON sent as another type is refused with the fix, not a riddle
        plain = await http.post(f"{API}/sensors/boom/commands/set_zero_type",
                                content=b'{"type": "relative"}', headers={
                                    **AUTH, "Content-Type": "text/plain"})
        assert_error(plain, 422, "bad_arguments")
        assert "Content-Type: application/json" in plain.json()["error"]
        # a key given twice is not a choice of the last one
        twice = await http.post(f"{API}/sensors/boom/commands/set_zero_type",
                                content=b'{"type": "relative", "type": "absolute"}',
                                headers={**AUTH, "Content-Type": "application/json"})
        assert_error(twice, 422, "bad_arguments")
        assert twice.json()["error"] == "the key 'type' is given twice; give each key once"
        # the series or protocol lacks it
        lacks = await post(http, "arm/commands/set_declination", {"degrees": 3})
        assert_error(lacks, 422, "unsupported")
        # unknown names
        assert_error(await post(http, "boom/commands/explode"), 404, "unknown_command")
        assert_error(await post(http, "nobody/commands/save"), 404, "unknown_sensor")
        # a native gyro calibration is over with its answer: nothing is busy after it
        assert (await post(http, "boom/commands/calibrate_gyro")).status_code == 200
        assert "busy_with" not in (await http.get(f"{API}/sensors/boom")).json()[
            "settings"]
        # the declination is sent rounded half away from zero, as the sensor shows it
        declination = await post(http, "boom/commands/set_declination", {"degrees": 0.25})
        assert declination.json()["answer"] == {"degrees": 0.3}
        assert ah.settings.declination == 0.3
        # read_settings names it as the settings do: declination (never "degrees")
        settings = (await post(http, "boom/commands/read_settings")).json()["answer"]
        assert settings["declination"] == 0.3 and "degrees" not in settings
        assert (await http.get(f"{API}/sensors/boom")).json()["settings"][
            "declination"] == 0.3
        # busy: during the save's deaf period
        saving = asyncio.create_task(post(http, "boom/commands/save"))
        await until(lambda: gateway.cache.snapshot("boom").busy)
        assert (await http.get(f"{API}/sensors/boom")).json()["settings"][
            "busy_with"] == "save"
        assert_error(await post(http, "boom/commands/calibrate_gyro"), 409, "busy")
        assert (await saving).status_code == 200
        # the sensor does not answer: a command that changes it was sent, and may have
        # been carried out ("unconfirmed": not sent again); a read is a timeout
        vg.faults.stalled = True
        assert_error(await post(http, "arm/commands/set_zero_type", {"type": "absolute"}),
                     502, "unconfirmed")
        assert_error(await post(http, "arm/commands/read_settings"), 504, "timeout")
        assert ah.settings.zero_type == "relative"  # nothing else happened to it


@pytest.mark.anyio
async def test_commands_turned_off_are_403(two_lines: Any) -> None:
    ah, _, buses = two_lines

    async with running(config(buses, allow_commands=False)) as gateway, \
            client(gateway) as http:
        response = await http.post(f"{API}/sensors/boom/commands/set_zero_type",
                                   json={"type": "relative"}, headers=AUTH)
        assert_error(response, 403, "forbidden")
        assert ah.settings.zero_type == "absolute"



# ------------------------------------------------------------------ live stream


async def sse_events(response: httpx.Response) -> AsyncIterator[tuple[str, dict[str, Any]]]:
    name, data = "message", ""
    async for line in response.aiter_lines():
        if line.startswith("event:"):
            name = line[6:].strip()
        elif line.startswith("data:"):
            data = line[5:].strip()
        elif not line and data:
            yield name, json.loads(data)
            name, data = "message", ""


@pytest.mark.anyio
async def test_stream_delivers_every_reading_at_the_poll_rate(two_lines: Any) -> None:
    _, _, buses = two_lines
    for b in buses:
        b["sensors"][0]["poll_hz"] = 20

    async with running(config(buses)) as gateway, client(gateway) as http:
        await until(lambda: all(s.seq >= 1 for s in gateway.cache.snapshots()))
        seen: dict[str, list[int]] = {"boom": [], "arm": []}
        async with http.stream("GET", f"{API}/stream") as response:
            assert response.headers["content-type"].startswith("text/event-stream")
            start = {s.name: s.seq for s in gateway.cache.snapshots()}
            async for name, event in sse_events(response):
                if name == "reading":
                    seen[event["sensor"]].append(event["seq"])
                if all(len(s) >= 30 for s in seen.values()):
                    break
        for sensor, seqs in seen.items():
            # every reading, in order, none skipped: the poll rate is the event rate
            later = [s for s in seqs if s > start[sensor]]
            assert later == list(range(later[0], later[0] + len(later))), sensor
        async with http.stream("GET", f"{API}/sensors/arm/stream") as response:
            async for name, event in sse_events(response):
                assert event["sensor"] == "arm"
                if name == "reading":
                    assert fields_of(event) and "mag" not in event
                    break
        response = await http.get(f"{API}/sensors/nobody/stream")
        assert_error(response, 404, "unknown_sensor")



@pytest.mark.anyio
async def test_a_stream_client_that_does_not_read_is_dropped(two_lines: Any) -> None:
    _, _, buses = two_lines
    buses[0]["sensors"][0]["poll_hz"] = 0  # as fast as the line goes

    async with running(config(buses)) as gateway:
        assert gateway.http is not None and gateway.http.hub is not None
        hub = gateway.http.hub
        # A client with a tiny receive window that never reads.
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
        sock.connect(("127.0.0.1", gateway.http.port))
        sock.sendall(f"GET {API}/sensors/boom/stream HTTP/1.1\r\n"
                     "Host: test\r\n\r\n".encode())
        try:
            await until(lambda: hub.dropped >= 1, timeout=60)
            await until(lambda: not hub.subscribers)
            # a reading client is served meanwhile
            async with client(gateway) as http:
                assert (await http.get(f"{API}/health")).status_code == 200
        finally:
            sock.close()
        await until(lambda: hub.open == 0)  # its stream ended with its connection



# ------------------------------------------------------------------ metrics, OpenAPI


@pytest.mark.anyio
async def test_metrics(two_lines: Any) -> None:
    _, vg, buses = two_lines

    async with running(config(buses)) as gateway, client(gateway) as http:
        await until(lambda: all(s.seq >= 2 for s in gateway.cache.snapshots()))
        vg.faults.stalled = True
        await until(lambda: gateway.cache.snapshot("arm").status.value == "offline",
                    timeout=20)
        buses_out = {b["name"]: b for b in (await http.get(f"{API}/buses")).json()}
        response = await http.get("/metrics")
        assert response.headers["content-type"].startswith("text/plain")
        samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
                   for family in text_string_to_metric_families(response.text)
                   for s in family.samples}
        # the version, from the one place it is written (the package)
        assert samples[("imu_gateway_build_info", (("version", __version__),))] == 1
        # every error kind from 0, so that rate() sees the first; the process's own
        for kind in ERROR_KINDS:
            assert ("imu_gateway_bus_errors_total", (("bus", "a"), ("kind", kind))) in samples
        assert samples[("process_resident_memory_bytes", ())] > 0
        # and Prometheus's own linter finds nothing to say
        promtool = shutil.which("promtool")
        assert promtool, "promtool is not installed (scripts/bootstrap --test installs it)"
        lint = subprocess.run([promtool, "check", "metrics"], input=response.text,
                              capture_output=True, text=True, timeout=60)
        assert lint.returncode == 0 and not lint.stdout.strip(), lint
        tx = samples[("imu_gateway_bus_transactions_total", (("bus", "a"),))]
        assert buses_out["a"]["transactions"] <= tx <= buses_out["a"]["transactions"] + 100
        assert samples[("imu_gateway_bus_port_open", (("bus", "b"),))] == 1
        assert samples[("imu_gateway_bus_late_writes_total", (("bus", "a"),))] == 0
        assert ("imu_gateway_bus_utilisation", (("bus", "a"),)) in samples
        assert ("imu_gateway_bus_queue_depth", (("bus", "a"),)) in samples
        assert samples[("imu_gateway_bus_errors_total",
                        (("bus", "b"), ("kind", "timeout")))] >= 1
        status = {labels: v for (name, labels), v in samples.items()
                  if name == "imu_gateway_sensor_status" and ("sensor", "arm") in labels}
        assert status == {(("sensor", "arm"), ("status", "offline")): 1.0,
                          (("sensor", "arm"), ("status", "ok")): 0.0,
                          (("sensor", "arm"), ("status", "stale")): 0.0}
        assert samples[("imu_gateway_sensor_rate_hz", (("sensor", "boom"),))] > 0
        latency = samples[("imu_gateway_sensor_latency_seconds", (("sensor", "boom"),))]
        timeout = samples[("imu_gateway_sensor_timeout_seconds", (("sensor", "boom"),))]
        assert 0 < latency <= timeout
        assert ("imu_gateway_sensor_late_answers_total", (("sensor", "arm"),)) in samples
        assert samples[("imu_gateway_sensor_age_seconds", (("sensor", "boom"),))] >= 0
        assert samples[("imu_gateway_frontend_requests_total", (("frontend", "http"),))] >= 2
        assert ("imu_gateway_frontend_clients", (("frontend", "http"),)) in samples



@pytest.mark.anyio
async def test_committed_openapi_document_is_what_the_app_serves(two_lines: Any) -> None:
    _, _, buses = two_lines
    committed = (ROOT / "openapi" / "openapi.json").read_text()
    assert openapi_json() == committed, "run scripts/openapi and commit the result"

    async with running(config(buses)) as gateway, client(gateway) as http:
        served = (await http.get("/openapi.json")).json()
        assert served == json.loads(committed)



@pytest.mark.anyio
async def test_a_taken_port_is_a_clear_startup_error(two_lines: Any) -> None:
    _, _, buses = two_lines
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]

        with pytest.raises(StartupError, match=f"http.listen 127.0.0.1:{port}: "):
            async with running(config(buses, listen=f"127.0.0.1:{port}")):
                pass



def test_busy_with_is_shown_only_while_the_sensor_is_busy() -> None:
    """settings.busy_with names the save or calibration under way, and goes once the
    busy period ended, whichever came first: the end, or the command's answer noted."""
    from imu_gateway.cache import Cache
    from imu_gateway.model import KnownSettings

    cache = Cache([("boom", 1000)])
    cache.set_state("boom", online=True, busy=True)
    cache.learn("boom", KnownSettings(busy_with="save", zero_type="relative"))
    assert cache.settings("boom").to_json() == {"busy_with": "save", "zero_type": "relative"}
    cache.set_state("boom", busy=False)
    assert cache.settings("boom").to_json() == {"zero_type": "relative"}
    # noted after its busy period ended (or a command that had none): never shown
    cache.learn("boom", KnownSettings(busy_with="calibrate_gyro"))
    assert cache.settings("boom").to_json() == {"zero_type": "relative"}
    cache.set_state("boom", busy=True)  # a later busy period starts with nothing named
    assert cache.settings("boom").to_json() == {"zero_type": "relative"}


@pytest.mark.anyio
async def test_readings_carry_the_derived_values() -> None:
    """The reading JSON's tilt from its own pitch and roll (a native sensor's exact
    32.52 and -3.5: to the last digit), the vibration null until the last second holds
    10 samples, then 0 for a sensor held still; the same in the sensor's detail."""
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(EXACT))
    imu = sensor(WireProtocol.NATIVE, Series.IMU, address=1, source=hold(EXACT))
    with simulated([ah, imu]) as line:
        cfg = config([bus("a", line.path, "native", [
            {"name": "boom", "series": "AH", "poll_hz": 15},
            {"name": "base", "series": "IMU", "address": 1, "poll_hz": 5}])])
        async with running(cfg) as gateway, client(gateway) as http:
            await until(lambda: gateway.cache.snapshot("boom").seq >= 1)
            first = (await http.get(f"{API}/sensors/boom/reading")).json()
            want_tilt, want_direction = exact_tilt()
            assert first["tilt"] == {"tilt": want_tilt, "tilt_direction": want_direction}
            if gateway.cache.snapshot("boom").seq < 10:
                assert first["vibration"] == {"vibration": None}  # null, not 0

            async def still() -> bool:
                got = (await http.get(f"{API}/sensors/boom/reading")).json()
                return bool(got["vibration"] == {"vibration": 0.0})
            await until(still)
            detail = (await http.get(f"{API}/sensors/boom")).json()
            assert detail["reading"]["tilt"] == first["tilt"]
            # an IMU has no angles, so no tilt; at 5 Hz never ten samples in a second
            await until(lambda: gateway.cache.snapshot("base").seq >= 12)
            base = (await http.get(f"{API}/sensors/base/reading")).json()
            assert "tilt" not in base and base["vibration"] == {"vibration": None}


def test_reading_groups_are_optional_and_never_null_in_the_openapi_schema() -> None:
    schema = json.loads(openapi_json())["components"]["schemas"]["ReadingOut"]
    groups = ("angles", "accel", "gyro", "mag", "quaternion", "tilt", "vibration")
    assert not set(groups) & set(schema["required"])
    for name in groups:
        assert "anyOf" not in schema["properties"][name], name
        assert schema["properties"][name]["$ref"].startswith("#/components/schemas/")


@pytest.mark.anyio
async def test_a_value_that_is_not_a_number_is_null_not_broken_json() -> None:
    """A Modbus float register can hold NaN; JSON cannot."""
    from dataclasses import replace

    from imu_gateway.model import Vector3

    assert READING.accel is not None
    odd = replace(READING, accel=Vector3(float("nan"), READING.accel.y, float("inf")))
    vg = sensor(WireProtocol.MODBUS, Series.VG, address=1, source=hold(odd))
    with simulated([vg]) as line:
        buses = [bus("b", line.path, "modbus", [{"name": "arm", "series": "VG"}])]

        async with running(config(buses)) as gateway, client(gateway) as http:
            await until(lambda: gateway.cache.snapshot("arm").seq >= 1)
            got = (await http.get(f"{API}/sensors/arm/reading")).json()
            assert got["accel"]["x"] is None and got["accel"]["z"] is None
            assert READING.accel is not None
            assert abs(got["accel"]["y"] - READING.accel.y) < 1e-6
            detail = await http.get(f"{API}/sensors/arm")
            assert detail.status_code == 200
            assert detail.json()["reading"]["accel"]["x"] is None



@pytest.mark.anyio
async def test_command_bodies_are_read_only_after_access_is_granted(two_lines: Any) -> None:
    """Auth and allow_commands come before the body is even read; a body is at most
    16 KiB."""
    _, _, buses = two_lines
    huge = b'{"type": "' + b"x" * 100_000 + b'"}'
    route = f"{API}/sensors/boom/commands/set_zero_type"
    json_type = {"Content-Type": "application/json"}

    async with running(config(buses, allow_commands=False)) as gateway, \
            client(gateway) as http:
        assert_error(await http.post(route, content=b"{not json", headers=json_type),
                     403, "forbidden")
    async with running(config(buses)) as gateway, client(gateway) as http:
        assert_error(await http.post(route, content=b"{not json", headers=json_type),
                     401, "unauthorised")
        assert_error(await http.post(route, content=huge, headers=json_type),
                     401, "unauthorised")
        assert_error(await http.post(route, content=huge,
                                     headers={**json_type, **AUTH}), 413, "too_large")
        # The other routes take no body: refused as soon as the headers announce one.
        for path in (f"{API}/health", f"{API}/sensors/boom", "/"):
            refused = await http.request("GET", path, content=b"x" * 10)
            assert_error(refused, 413, "too_large")
            assert refused.json()["error"] == f"GET {path} takes no body"
        # a method no route has: 405, its body unread
        assert_error(await http.request("DELETE", f"{API}/sensors", content=b"x" * 10),
                     405, "method_not_allowed")
        ok = await http.post(route, json={"type": "relative"}, headers=AUTH)
        assert ok.status_code == 200, ok.text
