"""GET and PUT /api/v1/config (docs/rest.md, "The config") through a real HTTP client
against a running gateway on a simulated line, its config in a real file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.harness import running, until
from support.readonly import read_only

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.passwords import hash_password
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

READING = Motion.from_seed(3).sample(10.0)
TOKEN = "t0ken-for-tests"
AUTH = {"Authorization": f"Bearer {TOKEN}"}

FILE = """\
# the plant's gateway
gateway_id: test
buses:
  - name: a   # the boom's line
    port: {port}
    protocol: native
    baudrate: 115200
    timeout_ms: 300
    sensors:
      - name: boom
        series: AH
mqtt:
  url: mqtt://127.0.0.1:1
  username: gateway
  password: ${{MQTT_PASSWORD}}   # from the environment
http:
  listen: 127.0.0.1:0
  token: {token}
"""




@pytest.fixture
def setup(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Any:
    monkeypatch.setenv("MQTT_PASSWORD", "the-real-password")
    a1 = make_sensor(WireProtocol.NATIVE, Series.AH, baud=115200, source=hold(READING))
    a2 = make_sensor(WireProtocol.NATIVE, Series.AH, address=1, baud=115200,
                     source=hold(READING))
    with simulated([a1, a2]) as line:
        path = tmp_path / "gateway.yaml"
        path.write_text(FILE.format(port=line.path, token=TOKEN))
        yield path


def client(gateway: Gateway) -> httpx.AsyncClient:
    assert gateway.http is not None
    return httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}",
                             timeout=15, headers=AUTH)


def added(config: dict[str, Any]) -> dict[str, Any]:
    config["buses"][0]["sensors"].append({"name": "boom2", "series": "AH", "address": 1})
    return config


@pytest.mark.anyio
async def test_get_shows_references_and_hides_literal_secrets(setup: Path) -> None:
    async with running(setup) as gw, client(gw) as http:
        got = (await http.get("/api/v1/config")).json()["config"]
        assert got["mqtt"]["password"] == "${MQTT_PASSWORD}"
        assert got["http"]["token"] == "***"
        raw = (await http.get("/api/v1/config")).text
        assert "the-real-password" not in raw and TOKEN not in raw
        no_token = await http.get("/api/v1/config", headers={"Authorization": ""})
        assert no_token.status_code == 401


@pytest.mark.anyio
async def test_put_adds_a_sensor_live_and_saves_comments_and_references(setup: Path) -> None:
    """The config sent back as GET gave it (secrets hidden), with a sensor more: it is
    served at once, the file keeps its comments and ${VAR}, the old one is .bak."""
    before = setup.read_text()
    async with running(setup) as gw, client(gw) as http:
        config = added((await http.get("/api/v1/config")).json()["config"])
        dry = await http.put("/api/v1/config?dry_run=1", json=config)
        assert dry.status_code == 200 and dry.json()["applied"] is False
        assert dry.json()["diff"]["sensors"]["added"] == [{"sensor": "boom2", "bus": "a"}]
        assert "boom2" not in gw.sensors and setup.read_text() == before
        answer = await http.put("/api/v1/config", json=config)
        assert answer.status_code == 200, answer.text
        body = answer.json()
        assert body["applied"] and body["saved"], body
        sensors = (await http.get("/api/v1/sensors")).json()
        assert [s["name"] for s in sensors] == ["boom", "boom2"]
        await until(lambda: gw.cache.snapshot("boom2").has_reading)
    text = setup.read_text()
    assert "# the plant's gateway" in text and "# the boom's line" in text
    assert "${MQTT_PASSWORD}" in text and "the-real-password" not in text
    assert f"token: {TOKEN}" in text  # the *** sent back kept the file's value
    assert "boom2" in text
    assert setup.with_name("gateway.yaml.bak").read_text() == before


@pytest.mark.anyio
async def test_a_broken_config_changes_nothing(setup: Path) -> None:
    before = setup.read_text()
    async with running(setup) as gw, client(gw) as http:
        config = (await http.get("/api/v1/config")).json()["config"]
        config["buses"][0]["baudrate"] = 12345
        config["buses"][0]["sensors"].append({"name": "boom", "series": "XY"})
        answer = await http.put("/api/v1/config", json=config)
        assert answer.status_code == 422
        problems = answer.json()["problems"]
        assert any(p.startswith("buses[0].baudrate:") for p in problems), problems
        assert any(p.startswith("buses[0].sensors[1].series:") for p in problems), problems
        bad_yaml = await http.put("/api/v1/config", content="buses: [")
        assert bad_yaml.status_code == 422 and "invalid YAML" in bad_yaml.json()["problems"][0]
        assert list(gw.sensors) == ["boom"] and gw.config.buses[0].baudrate == 115200
    assert setup.read_text() == before


@pytest.mark.anyio
async def test_a_read_only_file_is_applied_live_and_not_saved(setup: Path) -> None:
    before = setup.read_text()
    with read_only(setup.parent / "ro", {setup.name: before}):
        await _applied_not_saved(setup.parent / "ro" / setup.name)


async def _applied_not_saved(setup: Path) -> None:
    before = setup.read_text()
    async with running(setup) as gw, client(gw) as http:
        config = added((await http.get("/api/v1/config")).json()["config"])
        body = (await http.put("/api/v1/config", json=config)).json()
        assert body["applied"] and not body["saved"] and "not saved" in body["note"]
        assert "boom2" in gw.sensors
        assert "boom2" in [c["name"] for c in
                           (await http.get("/api/v1/config")).json()["config"]["buses"][0]
                           ["sensors"]]
    assert setup.read_text() == before


ROLES_TAIL = """\
  tokens:
    - {{token: {operator}, role: operator}}
    - {{token: {viewer}, role: viewer}}
  users:
    anna: {{role: admin, password: "{hash}"}}
"""


@pytest.mark.anyio
async def test_tokens_and_users_are_hidden_and_cannot_change_role_through_a_put(
        setup: Path) -> None:
    """``http.tokens`` is a list: each token is hidden (its role shown), and a ``***``
    sent back keeps the token that was at its place only while the entry around it is
    the same one. An admin who inserts a token before the others and sends the rest
    back hidden gets 422, not the viewer's token turned operator."""
    operator, viewer = "op-t0ken-secret-1", "viewer-t0ken-secret-2"
    setup.write_text(setup.read_text() + ROLES_TAIL.format(
        operator=operator, viewer=viewer, hash=hash_password("anna's password")))
    async with running(setup) as gw, client(gw) as http:
        shown = (await http.get("/api/v1/config", headers=AUTH)).json()["config"]
        text = json.dumps(shown)
        assert operator not in text and viewer not in text and "scrypt$" not in text
        assert shown["http"]["tokens"] == [{"token": "***", "role": "operator"},
                                           {"token": "***", "role": "viewer"}]
        assert shown["http"]["users"] == {"anna": {"role": "admin", "password": "***"}}
        same = await http.put("/api/v1/config", json=shown, headers=AUTH)
        assert same.status_code == 200, same.text  # sent back as it was: kept
        who = (await http.get("/api/v1/me", headers={"Authorization": f"Bearer {viewer}"}))
        assert who.json()["role"] == "viewer"
        shifted = json.loads(text)
        shifted["http"]["tokens"].insert(0, {"token": "a-new-t0ken-3", "role": "viewer"})
        refused = await http.put("/api/v1/config", json=shifted, headers=AUTH)
        assert refused.status_code == 422, refused.text
        assert any(p.startswith("http.tokens[1].token:") for p in refused.json()["problems"])
        who = (await http.get("/api/v1/me", headers={"Authorization": f"Bearer {viewer}"}))
        assert who.json()["role"] == "viewer"  # nothing changed
    assert viewer in setup.read_text() and "a-new-t0ken-3" not in setup.read_text()
