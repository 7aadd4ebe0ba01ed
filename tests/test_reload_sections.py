"""The sections a reload applies itself (docs/configuration.md, "Changing the config
while running"): ``http``, ``alarm_journal``, ``capture`` and ``hand_over_ms`` changed
through a real ``PUT /api/v1/config`` on a running gateway, on a simulated line, its
config in a real file; the effect seen from the side of a client."""

from __future__ import annotations

import json
import logging
import socket
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.harness import free_port, running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.passwords import hash_password
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

READING = Motion.from_seed(3).sample(10.0)
TOKEN = "adm1n-t0ken-for-tests"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
PASSWORD = "anna's password"

FILE = """\
gateway_id: test
buses:
  - name: a
    port: {port}
    protocol: native
    baudrate: 115200
    timeout_ms: 300
    sensors:
      - name: boom
        series: AH
        alarms:
          - {{name: tilt, field: pitch, above: -1000}}
alarm_journal: {journal}
capture:
  dir: {captures}
  pre_s: 1
  post_s: 0.2
http:
  listen: 127.0.0.1:0
  token: {token}
  allow_commands: true
  tokens:
    - {{token: old-viewer-t0ken, role: viewer}}
  users:
    anna: {{role: operator, password: "{hash}"}}
"""


@pytest.fixture
def setup(tmp_path: Path) -> Any:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, baud=115200, source=hold(READING))
    with simulated([sensor]) as line:
        path = tmp_path / "gateway.yaml"
        path.write_text(FILE.format(port=line.path, token=TOKEN, journal=tmp_path / "j1.jsonl",
                                    captures=tmp_path / "c1",
                                    hash=hash_password(PASSWORD)))
        yield path


def at(port: int, **headers: str) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}", timeout=15,
                             headers=headers or AUTH)


def port_of(gateway: Gateway) -> int:
    assert gateway.http is not None
    return gateway.http.port


async def put(gateway: Gateway, change: Any) -> dict[str, Any]:
    """The config as GET shows it (secrets hidden), changed by ``change``, PUT back."""
    async with at(port_of(gateway)) as http:
        config = (await http.get("/api/v1/config")).json()["config"]
        change(config)
        answer = await http.put("/api/v1/config", json=config)
    assert answer.status_code == 200, answer.text
    body: dict[str, Any] = answer.json()
    assert body["applied"] and body["needs_restart"] == [], body
    return body


async def role_of(gateway: Gateway, token: str) -> int | str:
    async with at(port_of(gateway), Authorization=f"Bearer {token}") as http:
        answer = await http.get("/api/v1/me")
    return answer.json()["role"] if answer.status_code == 200 else answer.status_code


@pytest.mark.anyio
async def test_tokens_and_users_change_at_once_without_a_restart(setup: Path) -> None:
    """A token added works at the next request, the one removed gets 401 at once, and
    a session of a user removed ends; the server is the same (same port)."""
    async with running(setup) as gw:
        port = port_of(gw)
        async with at(port, Authorization="") as http:
            login = await http.post("/api/v1/login", json={"user": "anna",
                                                           "password": PASSWORD})
        session = login.json()["token"]
        assert await role_of(gw, session) == "operator"
        assert await role_of(gw, "old-viewer-t0ken") == "viewer"

        def change(config: dict[str, Any]) -> None:
            config["http"]["tokens"] = [{"token": "new-admin-t0ken", "role": "admin"}]
            del config["http"]["users"]

        body = await put(gw, change)
        assert "http" in [c["name"] for c in body["diff"]["sections"]["changed"]]
        assert port_of(gw) == port and body["after_answer"] is None
        assert await role_of(gw, "new-admin-t0ken") == "admin"
        assert await role_of(gw, "old-viewer-t0ken") == 401
        assert await role_of(gw, session) == 401
        assert await role_of(gw, TOKEN) == "admin"  # (kept: sent back as ***)


@pytest.mark.anyio
async def test_a_new_journal_file_takes_the_transitions_from_the_switch_on(
        setup: Path) -> None:
    """The old file keeps what it had; the new one starts with the alarms' history
    kept in memory, then gets the next transition; nothing goes to the old one after."""
    old, new = setup.with_name("j1.jsonl"), setup.with_name("j2.jsonl")
    async with running(setup) as gw:
        await until(lambda: old.exists() and b"active" in old.read_bytes())
        before = old.read_bytes()
        body = await put(gw, lambda c: c.update(alarm_journal=str(new)))
        assert "alarm_journal" in body["diff"]["summary"]
        async with at(port_of(gw)) as http:
            acked = await http.post("/api/v1/alarms/boom/tilt/ack?by=tester")
        assert acked.status_code == 200, acked.text
        await until(lambda: new.exists() and b"tester" in new.read_bytes())
    lines = [json.loads(line) for line in new.read_bytes().splitlines()]
    assert [line["to"] for line in lines[-2:]] == ["active_unacked", "active_acked"], lines
    assert old.read_bytes() == before


@pytest.mark.anyio
async def test_a_capture_section_changed_is_applied_live(setup: Path) -> None:
    """A longer pre_s and another folder: the ring keeps its rows and grows, and the
    next capture is written to the new folder (the old one is no longer listed)."""
    folder = setup.with_name("c2")
    async with running(setup) as gw:
        assert gw.captures is not None
        captures = gw.captures
        await until(lambda: len(captures.rings["boom"].rows) > 5)
        body = await put(gw, lambda c: c["capture"].update(dir=str(folder), pre_s=3))
        assert "capture" in [c["name"] for c in body["diff"]["sections"]["changed"]]
        ring = captures.rings["boom"]
        assert ring.keep == 3 and len(ring.rows) > 5  # the rows it had, kept
        async with at(port_of(gw)) as http:
            armed = await http.post("/api/v1/captures")
            assert armed.status_code == 202, armed.text
            capture_id = armed.json()["id"]

            async def listed() -> bool:
                shown = (await http.get("/api/v1/captures")).json()
                return [c["id"] for c in shown] == [capture_id]

            await until(listed)
    assert (folder / f"{capture_id}.zip").exists()


@pytest.mark.anyio
async def test_hand_over_ms_is_applied_live_and_a_live_stream_still_gets_every_sample(
        setup: Path) -> None:
    """``hand_over_ms`` set and back to 0 by a PUT: the bus thread's window follows,
    nothing restarts, and an open live stream gets every sample, in order, in both."""
    async with running(setup) as gw:
        body = await put(gw, lambda c: c.update(hand_over_ms=40))
        assert "hand_over_ms" in [c["name"] for c in body["diff"]["sections"]["changed"]]
        assert gw.buses.writer.window == 0.04
        async with at(port_of(gw)) as http, \
                http.stream("GET", "/api/v1/sensors/boom/stream") as stream:
            seqs: list[int] = []
            async for line in stream.aiter_lines():
                if line.startswith("data: ") and '"seq"' in line:
                    seqs.append(json.loads(line[6:])["seq"])
                if len(seqs) >= 30:
                    break
        assert seqs == list(range(seqs[0], seqs[0] + 30)), seqs
        await put(gw, lambda c: c.update(hand_over_ms=0))
        assert gw.buses.writer.window == 0.0


@pytest.mark.anyio
async def test_a_new_listen_port_is_taken_after_the_answer(setup: Path) -> None:
    """The answer comes from the old port and says where the server goes; then the
    new port answers and the old one does not."""
    async with running(setup) as gw:
        old, new = port_of(gw), free_port()
        body = await put(gw, lambda c: c["http"].update(listen=f"127.0.0.1:{new}"))
        assert f"moves to 127.0.0.1:{new}" in body["after_answer"]
        await until(lambda: port_of(gw) == new)
        async with at(new) as http:
            assert (await http.get("/api/v1/health")).status_code == 200
            shown = (await http.get("/api/v1/config")).json()["config"]
            assert shown["http"]["listen"] == f"127.0.0.1:{new}"
        with pytest.raises(httpx.ConnectError):
            async with at(old) as http:
                await http.get("/api/v1/health")


@pytest.mark.anyio
async def test_a_listen_port_that_cannot_be_bound_leaves_the_server_where_it_was(
        setup: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "imu_gateway")
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    busy = taken.getsockname()[1]
    with taken:
        async with running(setup) as gw:
            port = port_of(gw)
            body = await put(gw, lambda c: c["http"].update(listen=f"127.0.0.1:{busy}"))
            assert f"moves to 127.0.0.1:{busy}" in body["after_answer"]
            await until(lambda: "not applied" in caplog.text)
            assert "cannot listen at 127.0.0.1:" in caplog.text
            async with at(port) as http:
                shown = (await http.get("/api/v1/config")).json()["config"]
            assert shown["http"]["listen"] == "127.0.0.1:0"
            assert gw.config.http is not None and gw.config.http.listen.port == 0
