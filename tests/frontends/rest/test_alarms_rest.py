"""Alarms over REST (docs/alarms.md, docs/rest.md) against the running gateway on a
simulated sensor, end to end: the simulated sensor leans past the limit (its source is
swapped for a held reading, as a lean would move it), the alarm goes active after its
on-delay, a client without the token cannot acknowledge it, an operator does, the
value comes back through the hysteresis, and the journal, the live stream, the
metrics and the journal's file tell the same story.

Waits are for events (the stream, the cache's sequence numbers, the file), never for
a fixed time."""

from __future__ import annotations

import asyncio
import json
import shutil
import subprocess
import time
from collections.abc import AsyncIterator
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families
from support.harness import running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Angles, Reading, Series, WireProtocol
from imu_gateway.simulator import SimSensor, hold, make_sensor, simulated

FAST = 115200
TOKEN = "t0ken-for-alarms"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
API = "/api/v1"
ON_DELAY = 0.3


def leaning(pitch: float) -> Any:
    return hold(Reading(angles=Angles(pitch, 0.0, 0.0)))


def config(port: str, journal: Path | None = None, **http: Any) -> dict[str, Any]:
    alarm = {"name": "boom_lean", "field": "pitch", "above": 5.0, "hysteresis": 0.5,
             "on_delay_s": ON_DELAY, "severity": "critical"}
    out: dict[str, Any] = {
        "gateway_id": "alarms",
        "buses": [{"name": "a", "port": port, "baudrate": FAST, "protocol": "native",
                   "timeout_ms": 300,
                   "sensors": [{"name": "boom", "series": "AH", "alarms": [alarm]}]}],
        "http": {"listen": "127.0.0.1:0", "token": TOKEN, **http}}
    if journal is not None:
        out["alarm_journal"] = str(journal)
    return out


def client(gateway: Gateway) -> httpx.AsyncClient:
    assert gateway.http is not None
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}", timeout=10)


@pytest.fixture
def boom() -> Any:
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST, source=leaning(1.0))
    with simulated([sim]) as line:
        yield sim, line.path


def states(answer: httpx.Response) -> dict[str, dict[str, Any]]:
    assert answer.status_code == 200, answer.text
    return {a["alarm"]: a for a in answer.json() if a["sensor"] == "boom"}


class AlarmEvents:
    """The ``alarm`` events of ``/api/v1/stream``, gathered as they come."""

    def __init__(self) -> None:
        self.seen: list[dict[str, Any]] = []
        self.task: asyncio.Task[None] | None = None

    async def read(self, http: httpx.AsyncClient, opened: asyncio.Event) -> None:
        async with http.stream("GET", f"{API}/stream") as response:
            name = ""
            opened.set()
            async for line in response.aiter_lines():
                if line.startswith("event:"):
                    name = line[6:].strip()
                elif line.startswith("data:") and name == "alarm":
                    self.seen.append(json.loads(line[5:]))

    async def wait_for(self, alarm: str, state: str) -> dict[str, Any]:
        def found() -> dict[str, Any] | None:
            return next((e for e in self.seen if e["alarm"] == alarm and e["state"] == state),
                        None)
        await until(lambda: found() is not None)
        event = found()
        assert event is not None
        return event


@pytest.fixture
async def events() -> AsyncIterator[AlarmEvents]:
    gathered = AlarmEvents()
    yield gathered
    if gathered.task is not None:
        gathered.task.cancel()


async def listen(http: httpx.AsyncClient, events: AlarmEvents) -> None:
    opened = asyncio.Event()
    events.task = asyncio.create_task(events.read(http, opened))
    await until(opened.is_set)


async def readings_pass(gateway: Gateway, n: int = 3) -> None:
    """Wait until ``n`` more samples of the boom have been evaluated."""
    seq = gateway.cache.snapshot("boom").seq
    await until(lambda: gateway.cache.snapshot("boom").seq >= seq + n)


def wall(iso: str) -> float:
    return datetime.fromisoformat(iso).timestamp()


def metrics(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


@pytest.mark.anyio
async def test_a_lean_raises_the_alarm_an_operator_acknowledges_it_and_it_clears(
        boom: tuple[SimSensor, str], events: AlarmEvents, tmp_path: Path) -> None:
    sim, port = boom
    journal = tmp_path / "alarms.jsonl"
    async with running(config(port, journal)) as gateway, client(gateway) as http:
        await listen(http, events)
        await readings_pass(gateway)
        before = states(await http.get(f"{API}/alarms"))
        assert before["boom_lean"] == {
            "sensor": "boom", "alarm": "boom_lean", "field": "pitch", "severity": "critical",
            "state": "normal", "active": False, "acked": True, "value": None, "limit": None,
            "since": None, "latch": False}
        assert before["communication"]["state"] == "normal"
        assert list(before) == ["boom_lean", "communication"]

        leaned_at = time.time()
        sim.source = leaning(10.0)
        raised = await events.wait_for("boom_lean", "active_unacked")
        assert raised["from"] == "normal" and raised["by"] is None
        assert raised["value"] == 10.0 and raised["limit"] == 5.0
        # the on-delay: not active before the lean had held for it (to the millisecond
        # of the stream's time stamps)
        assert wall(raised["since"]) >= leaned_at + ON_DELAY - 0.002

        scraped = await http.get("/metrics")
        samples = metrics(scraped.text)
        assert samples[("imu_gateway_alarm_active", (("alarm", "boom_lean"),
                        ("sensor", "boom"), ("severity", "critical")))] == 1
        assert samples[("imu_gateway_alarm_active", (("alarm", "communication"),
                        ("sensor", "boom"), ("severity", "critical")))] == 0
        assert samples[("imu_gateway_alarm_transitions_total", (("alarm", "boom_lean"),
                        ("sensor", "boom")))] == 1
        assert samples[("imu_gateway_alarm_journal_errors_total", ())] == 0
        promtool = shutil.which("promtool")
        assert promtool, "promtool is not installed (scripts/bootstrap --test installs it)"
        lint = subprocess.run([promtool, "check", "metrics"], input=scraped.text,
                              capture_output=True, text=True, timeout=60)
        assert lint.returncode == 0 and not lint.stdout.strip(), lint

        # from the side of a client without the operator's token
        ack = f"{API}/alarms/boom/boom_lean/ack"
        for headers in ({}, {"Authorization": "Bearer wrong"}):
            refused = await http.post(ack, headers=headers)
            assert refused.status_code == 401 and refused.json()["kind"] == "unauthorised"
            assert refused.headers["www-authenticate"] == "Bearer"
        refused = await http.post(ack, params={"access_token": TOKEN})  # (streams only)
        assert refused.status_code == 401
        assert states(await http.get(f"{API}/alarms"))["boom_lean"]["state"] == \
            "active_unacked"

        acked = await http.post(ack, headers=AUTH, params={"by": "alice"})
        assert acked.status_code == 200, acked.text
        assert (acked.json()["state"], acked.json()["acked"], acked.json()["active"]) == \
            ("active_acked", True, True)
        event = await events.wait_for("boom_lean", "active_acked")
        assert event["by"] == "alice (rest 127.0.0.1, http.token)"
        again = await http.post(ack, headers=AUTH)
        assert again.status_code == 409 and again.json()["kind"] == "nothing_to_acknowledge"
        unknown = await http.post(f"{API}/alarms/boom/nope/ack", headers=AUTH)
        assert unknown.status_code == 404 and unknown.json()["kind"] == "unknown_alarm"
        unknown = await http.post(f"{API}/alarms/nope/boom_lean/ack", headers=AUTH)
        assert unknown.status_code == 404 and unknown.json()["kind"] == "unknown_sensor"

        # back inside the limit but not through the hysteresis (4.7 > 4.5): still active
        sim.source = leaning(4.7)
        await until(lambda: gateway.cache.snapshot("boom").reading is not None and
                    gateway.cache.snapshot("boom").reading.angles.pitch == 4.7)  # type: ignore[union-attr]
        await readings_pass(gateway)
        assert states(await http.get(f"{API}/alarms"))["boom_lean"]["state"] == "active_acked"
        sim.source = leaning(4.0)
        cleared = await events.wait_for("boom_lean", "normal")
        assert cleared["from"] == "active_acked" and cleared["value"] == 4.0

        everything = (await http.get(f"{API}/alarms/journal")).json()
        assert [(t["from"], t["to"], t["by"]) for t in everything] == [
            ("normal", "active_unacked", None),
            ("active_unacked", "active_acked", "alice (rest 127.0.0.1, http.token)"),
            ("active_acked", "normal", None)]
        since = await http.get(f"{API}/alarms/journal", params={"since": everything[1]["ts"]})
        assert since.json() == everything[1:]
        epoch = await http.get(f"{API}/alarms/journal",
                               params={"since": wall(everything[2]["ts"])})
        assert epoch.json() == everything[2:]
        bad = await http.get(f"{API}/alarms/journal", params={"since": "yesterday"})
        assert bad.status_code == 422 and bad.json()["kind"] == "bad_arguments"
        await until(lambda: journal.exists() and len(journal.read_text().splitlines()) == 3)
    # the file holds the same, and stopping the gateway (its sensor gone from the bus)
    # raised no communication alarm
    lines = [json.loads(line) for line in journal.read_text().splitlines()]
    assert lines == everything


@pytest.mark.anyio
async def test_an_unacknowledged_alarm_is_still_there_after_a_restart(
        boom: tuple[SimSensor, str], tmp_path: Path) -> None:
    sim, port = boom
    journal = tmp_path / "alarms.jsonl"
    sim.source = leaning(30.0)
    async with running(config(port, journal)) as gateway, client(gateway) as http:
        await until(lambda: gateway.alarm_states()[0].active)
        first = states(await http.get(f"{API}/alarms"))["boom_lean"]
        await until(lambda: journal.exists() and journal.read_text().count("\n") == 1)
    sim.source = leaning(1.0)  # it came back while the gateway was down
    async with running(config(port, journal)) as gateway, client(gateway) as http:
        # It starts where it was (a fresh alarm would stay normal at 1.0), and the first
        # sample clears it: returned to normal, and still unacknowledged.
        await until(lambda: gateway.alarm_states()[0].state.value == "rtn_unacked")
        past = (await http.get(f"{API}/alarms/journal")).json()
        assert [(t["from"], t["to"], t["value"]) for t in past] == [
            ("normal", "active_unacked", 30.0), ("active_unacked", "rtn_unacked", 1.0)]
        assert past[0]["ts"] == first["since"]
        acked = await http.post(f"{API}/alarms/boom/boom_lean/ack", headers=AUTH)
        assert acked.json()["state"] == "normal"


@pytest.mark.anyio
async def test_the_communication_alarm_follows_a_sensor_that_stops_answering(
        boom: tuple[SimSensor, str], events: AlarmEvents) -> None:
    sim, port = boom
    async with running(config(port)) as gateway, client(gateway) as http:
        await listen(http, events)
        await readings_pass(gateway)
        # a gateway that starts raises none: "offline" before the first try is no alarm
        assert (await http.get(f"{API}/alarms/journal")).json() == []
        sim.faults.stalled = True
        raised = await events.wait_for("communication", "active_unacked")
        assert (raised["field"], raised["severity"], raised["value"]) == (None, "critical",
                                                                          None)
        sim.faults.stalled = False
        back = await events.wait_for("communication", "rtn_unacked")
        assert back["from"] == "active_unacked"
        acked = await http.post(f"{API}/alarms/boom/communication/ack", headers=AUTH)
        assert acked.status_code == 200 and acked.json()["state"] == "normal"


@pytest.mark.anyio
async def test_without_a_token_nobody_acknowledges(boom: tuple[SimSensor, str]) -> None:
    _, port = boom
    plain = config(port)
    del plain["http"]["token"]
    async with running(plain) as gateway, client(gateway) as http:
        refused = await http.post(f"{API}/alarms/boom/boom_lean/ack",
                                  headers={"Authorization": "Bearer anything"})
        assert refused.status_code == 403 and refused.json()["kind"] == "forbidden"
        assert "http.token" in refused.json()["error"]
