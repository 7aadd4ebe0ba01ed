"""Event capture through REST (docs/alarms.md, "Captures"; docs/rest.md): a capture
taken with ``POST /api/v1/captures`` holds every sample of every sensor from ``pre_s``
before to ``post_s`` after, and every frame of every line; the list, the download,
ids that name no path, retention, and a disk that will not take it.

A real HTTP client (httpx) against the running gateway on simulated sensors."""

from __future__ import annotations

import asyncio
import csv
import io
import json
import logging
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from support.harness import expected, running, tolerance, until
from support.readonly import read_only

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
READING = Motion.from_seed(5).sample(3.0)
TOKEN = "t0ken-for-capture-tests"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
API = "/api/v1"
PRE_S, POST_S, POLL_HZ = 1.0, 0.5, 20.0


def config(buses: list[dict[str, Any]], folder: Path, **capture: Any) -> dict[str, Any]:
    return {"gateway_id": "cap", "buses": buses,
            "http": {"listen": "127.0.0.1:0", "token": TOKEN, "allow_commands": True},
            "capture": {"dir": str(folder), "pre_s": PRE_S, "post_s": POST_S, **capture}}


def line(name: str, port: str, protocol: str, sensor: str, series: str) -> dict[str, Any]:
    return {"name": name, "port": port, "baudrate": FAST, "protocol": protocol,
            "timeout_ms": 300, "sensors": [{"name": sensor, "series": series,
                                            "poll_hz": POLL_HZ}]}


def client(gateway: Gateway) -> httpx.AsyncClient:
    assert gateway.http is not None
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}", timeout=10)


@pytest.fixture
def two_lines() -> Iterator[tuple[Any, list[dict[str, Any]]]]:
    """A native AH and a Modbus VG, each on its own line, holding one reading."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST, source=hold(READING))
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, address=1, baud=FAST,
                     source=hold(READING))
    with simulated([ah]) as a, simulated([vg]) as b:
        yield (ah, vg), [line("a", a.path, "native", "boom", "AH"),
                         line("b", b.path, "modbus", "arm", "VG")]


async def take(http: httpx.AsyncClient) -> dict[str, Any]:
    """POST a capture and wait until it is listed; its list entry."""
    posted = await http.post(f"{API}/captures", headers=AUTH)
    assert posted.status_code == 202, posted.text
    capture_id = posted.json()["id"]
    found: list[dict[str, Any]] = []

    async def listed() -> bool:
        found[:] = [c for c in (await http.get(f"{API}/captures")).json()
                    if c["id"] == capture_id]
        return bool(found)

    await until(listed, timeout=10)
    return found[0]


def table(archive: zipfile.ZipFile, name: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(archive.read(name).decode("utf-8"))))


@pytest.mark.anyio
async def test_a_capture_holds_pre_s_before_and_post_s_after_the_trigger(
        two_lines: Any, tmp_path: Path) -> None:
    (ah, vg), buses = two_lines
    folder = tmp_path / "captures"
    async with running(config(buses, folder)) as gateway, client(gateway) as http:
        # the ring is full: more than pre_s of samples
        await until(lambda: all(s.seq >= POLL_HZ * (PRE_S + 0.5)
                                for s in gateway.cache.snapshots()))
        refused = await http.post(f"{API}/captures")  # no token: an operator's only
        assert refused.status_code == 401 and refused.json()["kind"] == "unauthorised"
        before = time.time()
        entry = await take(http)
        response = await http.get(f"{API}/captures/{entry['id']}")
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/zip"
    assert entry["trigger"] == "manual" and entry["size"] == len(response.content)
    archive = zipfile.ZipFile(io.BytesIO(response.content))
    assert sorted(archive.namelist()) == ["arm.csv", "boom.csv", "frames.jsonl", "meta.json"]
    meta = json.loads(archive.read("meta.json"))
    at = meta["trigger"]["t"]
    assert before <= at <= time.time() and meta["trigger"]["reason"] == "manual"
    assert meta["version"] and [b["name"] for b in meta["buses"]] == ["a", "b"]
    assert TOKEN not in response.content.decode("latin-1")  # no secret in it, even zipped
    for zipped in archive.namelist():
        assert TOKEN.encode() not in archive.read(zipped)
    for name, sim in (("boom", ah), ("arm", vg)):
        rows = [r for r in table(archive, f"{name}.csv") if r["kind"] == "reading"]
        wire = [float(r["wire_s"]) for r in rows]
        # every sample: consecutive seqs, from pre_s before to post_s after the trigger
        seqs = [int(r["seq"]) for r in rows]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), seqs
        period = 1 / POLL_HZ
        assert at - PRE_S <= wire[0] <= at - PRE_S + 3 * period, (wire[0] - at)
        assert at + POST_S - 3 * period <= wire[-1] <= at + POST_S, (wire[-1] - at)
        assert all(float(r["wire_s"]) <= float(r["receive_s"]) for r in rows)
        assert rows[0]["wire_time"].endswith("Z") and rows[0]["status"] == "ok"
        want = expected(sim)
        protocol = sim.protocol
        for field, value in want.items():
            assert abs(float(rows[-1][field]) - value) <= tolerance(protocol, field, value)
        if name == "arm":  # a VG has no magnetic field: no column for it
            assert "mag_x" not in rows[0]
    frames = [json.loads(x) for x in archive.read("frames.jsonl").decode().splitlines()]
    for bus in ("a", "b"):
        mine = [f for f in frames if f["bus"] == bus]
        directions = {f["dir"] for f in mine}
        assert {"tx", "rx"} <= directions, directions
        assert all(at - PRE_S <= f["t"] <= at + POST_S for f in mine)
        # as many answers as requests in the window, give or take the ends
        assert abs(sum(f["dir"] == "tx" for f in mine) - POLL_HZ * (PRE_S + POST_S)) <= 4
        assert all(bytes.fromhex(f["hex"]) for f in mine)


async def raw_get(port: int, target: str) -> tuple[int, bytes]:
    """A GET of ``target`` exactly as written (an HTTP client library would resolve
    ``..`` itself): the status and the whole answer."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {target} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".encode())
    await writer.drain()
    answer = await reader.read()
    writer.close()
    return int(answer.split(b" ", 2)[1]), answer


@pytest.mark.anyio
async def test_an_id_names_no_path_outside_the_folder(two_lines: Any, tmp_path: Path) -> None:
    """A client that tries to reach another file through the id gets a 404, and
    never the file: not one outside the folder, nor one in it the gateway did not
    write."""
    _, buses = two_lines
    folder = tmp_path / "captures"
    secret = b"PK-not-yours"
    (tmp_path / "secret.zip").write_bytes(secret)
    folder.mkdir()
    (folder / ".20260101T000000000Z.zip").write_bytes(secret)  # not a capture's name
    async with running(config(buses, folder, post_s=0)) as gateway:
        assert gateway.http is not None
        for tail in ("..%2Fsecret", "..%2Fsecret.zip", "%2e%2e%2fsecret", "..%5csecret",
                     "..%2f..%2fetc%2fpasswd", "%2Fetc%2Fpasswd", "..", "%2e%2e",
                     ".20260101T000000000Z", "20260101T000000000Z",
                     "20260101T000000000Z%2F..%2F..%2Fsecret", "../secret", "../../secret.zip",
                     "captures/../secret.zip"):
            status, answer = await raw_get(gateway.http.port, f"{API}/captures/{tail}")
            assert status == 404, (tail, answer[:300])
            assert secret not in answer and b"application/zip" not in answer, tail


@pytest.mark.anyio
async def test_a_read_only_folder_is_one_warning_and_a_counter(
        two_lines: Any, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    _, buses = two_lines
    folder = tmp_path / "captures"
    with read_only(folder), caplog.at_level(logging.WARNING, "imu_gateway.capture"):
        async with running(config(buses, folder, post_s=0.1)) as gateway, \
                client(gateway) as http:
            await until(lambda: all(s.seq >= 5 for s in gateway.cache.snapshots()))
            for _ in range(2):
                posted = await http.post(f"{API}/captures", headers=AUTH)
                assert posted.status_code == 202
                captures = gateway.captures
                assert captures is not None
                failed = captures.counts["failed"]
                await until(lambda: captures.counts["failed"] > failed)  # noqa: B023
            # the buses and the other routes went on
            seqs = {s.name: s.seq for s in gateway.cache.snapshots()}
            await until(lambda: all(s.seq > seqs[s.name] + 5
                                    for s in gateway.cache.snapshots()))
            assert (await http.get(f"{API}/captures")).json() == []
            assert (await http.get(f"{API}/sensors/boom/reading")).status_code == 200
            metrics = (await http.get("/metrics")).text
    samples = {s.name: s.value for family in text_string_to_metric_families(metrics)
               for s in family.samples}
    assert samples["imu_gateway_capture_failures_total"] >= 2
    assert samples["imu_gateway_capture_written_total"] == 0
    warnings = [r for r in caplog.records if r.name == "imu_gateway.capture"]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert str(folder) in warnings[0].getMessage()


@pytest.mark.anyio
async def test_retention_deletes_the_oldest_first(two_lines: Any, tmp_path: Path) -> None:
    _, buses = two_lines
    folder = tmp_path / "captures"
    async with running(config(buses, folder, post_s=0, max_files=2)) as gateway, \
            client(gateway) as http:
        await until(lambda: all(s.seq >= 5 for s in gateway.cache.snapshots()))
        taken = [(await take(http))["id"] for _ in range(3)]
        listed = [c["id"] for c in (await http.get(f"{API}/captures")).json()]
        assert listed == taken[:0:-1]  # the newest first; the first one is gone
        assert sorted(p.name for p in folder.iterdir()) == [f"{i}.zip" for i in taken[1:]]
        gone = await http.get(f"{API}/captures/{taken[0]}")
        assert gone.status_code == 404
        # the list and the trigger share a path: a 405 names both methods
        other = await http.put(f"{API}/captures", headers=AUTH)
        assert other.status_code == 405 and other.headers["allow"] == "GET, POST"


@pytest.mark.anyio
async def test_an_alarm_that_becomes_active_takes_a_capture(tmp_path: Path) -> None:
    """``capture.on_alarms`` names an alarm: when a lean makes it active, a capture is
    taken with the alarm as its trigger, holding ``pre_s`` of samples before it (the
    moments that led there) and the lean after it."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST, source=hold(READING))
    folder = tmp_path / "captures"
    with simulated([ah]) as sim:
        sim.call(ah.lean, 1.0, 0.0).result(5)  # upright: the alarm is normal
        bus = line("a", sim.path, "native", "boom", "AH")
        bus["sensors"][0]["alarms"] = [{"name": "boom_lean", "field": "tilt", "above": 5.0,
                                        "hysteresis": 0.5},
                                       {"name": "other", "field": "pitch", "above": 80.0}]
        cfg = config([bus], folder, on_alarms=["boom_lean"])
        async with running(cfg) as gateway, client(gateway) as http:
            await until(lambda: gateway.cache.snapshot("boom").seq >= POLL_HZ * (PRE_S + 0.5))
            assert (await http.get(f"{API}/captures")).json() == []
            sim.call(ah.lean, 7.5, 0.0).result(5)
            found: list[dict[str, Any]] = []

            async def listed() -> bool:
                found[:] = (await http.get(f"{API}/captures")).json()
                return bool(found)

            await until(listed, timeout=15)
            response = await http.get(f"{API}/captures/{found[0]['id']}")
            states = {s["alarm"]: s["state"] for s in (await http.get(f"{API}/alarms")).json()
                      if s["sensor"] == "boom"}
    assert len(found) == 1 and found[0]["trigger"] == "alarm", found
    assert found[0]["alarm"] == "boom/boom_lean"
    assert states["boom_lean"] == "active_unacked" and states["other"] == "normal"
    archive = zipfile.ZipFile(io.BytesIO(response.content))
    at = json.loads(archive.read("meta.json"))["trigger"]["t"]
    rows = [r for r in table(archive, "boom.csv") if r["kind"] == "reading"]
    wire = [float(r["wire_s"]) for r in rows]
    period = 1 / POLL_HZ
    assert wire[0] <= at - PRE_S + 3 * period, wire[0] - at  # pre_s before the alarm
    before = [r for r in rows if float(r["wire_s"]) < at - 2 * period]
    after = [r for r in rows if float(r["wire_s"]) >= at]
    assert before and all(abs(float(r["pitch"]) - 1.0) < 0.01 for r in before)
    assert after and abs(float(after[-1]["pitch"]) - 7.5) < 0.01
