"""The address and baud change wizards (docs/wizards.md, "Address and baud rate") end to
end: a real HTTP client against a gateway started from a real config file, on simulated
sensors that answer only at their own address and rate.  After the procedure the
sensor is at the new address or rate, the config (``GET /api/v1/config`` and the file,
its comments kept) says so, and readings flow.  What the bus cannot take is refused
before anything is sent; an operator, who may not change the config, is refused."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.harness import until

from imu_gateway.app import Gateway
from imu_gateway.config import load_config
from imu_gateway.config.loading import ConfigSource
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

READING = Motion.from_seed(5).sample(3.0)
FAST = 115200
ADMIN, OPERATOR = "admin-t0ken-for-wizard-tests", "operator-t0ken-for-wizard-tests"
API = "/api/v1"

FILE = """\
# the plant's gateway
gateway_id: wiz
buses:
  - name: line   # the boom's line
    port: {port}
    protocol: {protocol}
    baudrate: 115200
    timeout_ms: 300
    sensors:
{sensors}
http:
  listen: 127.0.0.1:0
  allow_commands: true
  tokens:
    - {{token: {admin}, role: admin}}
    - {{token: {operator}, role: operator}}
"""


def sensor_lines(names_addresses: list[tuple[str, int]]) -> str:
    return "".join(f"      - name: {name}   # {name}'s own line\n        series: VG\n"
                   f"        address: {address}\n        poll_hz: 20\n"
                   for name, address in names_addresses)


@contextlib.asynccontextmanager
async def gateway_from(tmp_path: Path, protocol: WireProtocol, sensors: list[SimSensor],
                       names: list[str]) -> AsyncIterator[tuple[Gateway, httpx.AsyncClient,
                                                                Path]]:
    with simulated(sensors) as sim:
        path = tmp_path / "gateway.yaml"
        path.write_text(FILE.format(
            port=sim.path, protocol=protocol.name.lower(), admin=ADMIN, operator=OPERATOR,
            sensors=sensor_lines([(n, s.address) for n, s in zip(names, sensors,
                                                                         strict=True)])))
        gateway = Gateway(load_config(path), ConfigSource.read(path))
        stop = asyncio.Event()
        task = asyncio.create_task(gateway.run(stop))
        try:
            await until(lambda: gateway.http is not None and gateway.http.listening)
            assert gateway.http is not None
            await until(lambda: all(gateway.cache.snapshot(n).seq >= 1 for n in names))
            async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{gateway.http.port}",
                                         timeout=30) as http:
                yield gateway, http, path
        finally:
            stop.set()
            await asyncio.wait_for(task, 15)


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


async def run_to_end(http: httpx.AsyncClient, procedure: str,
                     body: dict[str, Any]) -> list[dict[str, Any]]:
    """Start it as the admin; its states from its Server-Sent Events, until the end."""
    answer = await http.post(f"{API}/sensors/boom/procedures/{procedure}", json=body,
                             headers=bearer(ADMIN))
    assert answer.status_code == 201, answer.text
    seen: list[dict[str, Any]] = []
    async with http.stream("GET", f"{answer.headers['location']}/events") as stream:
        async for line in stream.aiter_lines():
            if line.startswith("data: "):
                seen.append(json.loads(line.removeprefix("data: ")))
    return seen


def held(protocol: WireProtocol, address: int | None = None) -> SimSensor:
    return make_sensor(protocol, Series.VG, address, baud=FAST, source=hold(READING))


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", [WireProtocol.NATIVE, WireProtocol.MODBUS])
async def test_an_address_change_moves_the_sensor_and_the_config(
        tmp_path: Path, protocol: WireProtocol) -> None:
    sensor = held(protocol)
    async with gateway_from(tmp_path, protocol, [sensor], ["boom"]) as (gw, http, path):
        seen = await run_to_end(http, "change_address", {"address": 7})
        last = seen[-1]
        assert last["state"] == "done", last
        assert last["steps"] == ["set_address", "config", "reading"]
        assert (last["answers"]["config"]["applied"], last["answers"]["config"]["saved"]) \
            == (True, True)
        assert sensor.address == 7  # the sensor itself moved
        shown = (await http.get(f"{API}/config", headers=bearer(ADMIN))).json()["config"]
        assert shown["buses"][0]["sensors"][0]["address"] == 7
        text = path.read_text()
        assert "    address: 7\n" in text and "# boom's own line" in text
        assert "# the plant's gateway" in text  # the file's comments are kept
        assert load_config(path).buses[0].sensors[0].address == 7
        # the gateway talks to it at the new address from the config: readings flow
        seq = gw.cache.snapshot("boom").seq
        await until(lambda: gw.cache.snapshot("boom").seq >= seq + 5)
        assert gw.sensor_stats("boom").address == 7


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", [WireProtocol.NATIVE, WireProtocol.MODBUS])
async def test_a_baud_change_moves_the_sensor_and_the_bus(
        tmp_path: Path, protocol: WireProtocol) -> None:
    sensor = held(protocol)
    async with gateway_from(tmp_path, protocol, [sensor], ["boom"]) as (gw, http, path):
        seen = await run_to_end(http, "change_baudrate", {"baudrate": 38400})
        assert seen[-1]["state"] == "done", seen[-1]
        assert sensor.baud == 38400  # it answers at 38400 only (the simulated line)
        shown = (await http.get(f"{API}/config", headers=bearer(ADMIN))).json()["config"]
        assert shown["buses"][0]["baudrate"] == 38400
        assert "  baudrate: 38400\n" in path.read_text()
        assert "# the boom's line" in path.read_text()
        seq = gw.cache.snapshot("boom").seq
        await until(lambda: gw.cache.snapshot("boom").seq >= seq + 5)
        assert [b.baudrate for b in gw.stats() if b.name == "line"] == [38400]


@pytest.mark.anyio
async def test_a_baud_change_on_a_shared_bus_is_refused_naming_the_others(
        tmp_path: Path) -> None:
    boom, arm = held(WireProtocol.NATIVE, 0), held(WireProtocol.NATIVE, 1)
    async with gateway_from(tmp_path, WireProtocol.NATIVE, [boom, arm],
                            ["boom", "arm"]) as (_, http, path):
        before = path.read_text()
        refused = await http.post(f"{API}/sensors/boom/procedures/change_baudrate",
                                  json={"baudrate": 38400}, headers=bearer(ADMIN))
        assert refused.status_code == 422 and refused.json()["kind"] == "bad_arguments"
        assert refused.json()["error"].startswith(
            "bus line has other sensors (arm), which would stay at 115200 baud and go "
            "offline")
        taken = await http.post(f"{API}/sensors/boom/procedures/change_address",
                                json={"address": 1}, headers=bearer(ADMIN))
        assert taken.status_code == 422
        assert "address 1 is taken on bus line by arm" in taken.json()["error"]
        assert boom.writes_heard == {} and (boom.baud, boom.address) == (FAST, 0)
        assert path.read_text() == before


@pytest.mark.anyio
async def test_an_operator_may_not_change_the_address(tmp_path: Path) -> None:
    """Changing the config is an admin's: an operator (who may run the calibrations)
    is refused, and nothing is sent."""
    sensor = held(WireProtocol.NATIVE)
    async with gateway_from(tmp_path, WireProtocol.NATIVE, [sensor], ["boom"]) as (_, http,
                                                                                  _path):
        url = f"{API}/sensors/boom/procedures/change_address"
        operator = await http.post(url, json={"address": 7}, headers=bearer(OPERATOR))
        assert (operator.status_code, operator.json()["kind"]) == (403, "forbidden")
        assert "this needs admin" in operator.json()["error"]
        nobody = await http.post(url, json={"address": 7})
        assert nobody.status_code == 401
        assert sensor.writes_heard == {} and sensor.address == 0


@pytest.mark.anyio
async def test_a_lost_answer_is_read_back_never_sent_again_and_the_config_kept(
        tmp_path: Path) -> None:
    """The sensor takes the new address but its answer is lost: the procedure does not
    send set_address again on a guess; it reads back, hears nothing at the old address,
    and fails saying where the sensor may be.  The config is not changed."""
    sensor = held(WireProtocol.NATIVE)
    async with gateway_from(tmp_path, WireProtocol.NATIVE, [sensor], ["boom"]) as (_, http,
                                                                                  path):
        before = path.read_text()
        sensor.faults.drop_rate = 1.0  # every answer from now on is lost
        last = (await run_to_end(http, "change_address", {"address": 7}))[-1]
        assert (last["state"], last["kind"]) == ("failed", "unconfirmed"), last
        assert "the read back was not answered either: boom may be at address 7 now, or " \
               "still at address 0. The config was not changed" in last["error"]
        assert sensor.writes_heard["set_address"] == 1 and sensor.address == 7
        assert path.read_text() == before
