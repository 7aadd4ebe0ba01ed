"""Settings after a power cycle or a port loss, as the clients see them.

A zero type set ``relative`` and never saved is ``absolute`` again after the sensor
loses power.  The gateway cannot see a power cut, only that the sensor stopped
answering (or that its port went away): from then on what it learned of the sensor's
settings is unknown, and the bus reads them by itself (``read_settings``) once the
sensor answers again.  Checked from the clients' side: REST, the retained MQTT
settings topic on a real mosquitto, and Modbus TCP register 1000 (0xFFFF: unknown),
with the simulator standing in for the sensor and its USB adapter.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import httpx
import pytest
from pymodbus.client import AsyncModbusTcpClient
from support.broker import Mosquitto, Recorder, recording
from support.harness import running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, SimulatorThread, make_sensor, simulated

FAST = 115200
TOKEN = "settings-token"
GID = "gw"
UNIT = 1  # the sensor's Modbus TCP unit
ZERO_TYPE_REGISTER = 1000  # 0 absolute, 1 relative, 0xFFFF unknown (register-map.md)
UNKNOWN = 0xFFFF


def _config(port: str, protocol: str, address: int, broker: Mosquitto) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "line", "port": port, "baudrate": FAST, "protocol": protocol,
                       "timeout_ms": 300,
                       "sensors": [{"name": "ah", "series": "AH", "address": address,
                                    "poll_hz": 20, "unit_id": UNIT}]}],
            "http": {"listen": "127.0.0.1:0", "token": TOKEN, "allow_commands": True},
            "modbus": {"listen": "127.0.0.1:0"},
            "mqtt": {"url": broker.url}}


class Clients:
    """The three ways a client sees the sensor's zero type."""

    def __init__(self, gateway: Gateway, http: httpx.AsyncClient,
                 modbus: AsyncModbusTcpClient, mqtt: Recorder) -> None:
        self.gateway, self.http, self.modbus, self.mqtt = gateway, http, modbus, mqtt

    async def rest(self) -> dict[str, Any]:
        response = await self.http.get("/api/v1/sensors/ah")
        assert response.status_code == 200, response.text
        body: dict[str, Any] = response.json()
        return body

    async def register(self) -> int:
        answer = await self.modbus.read_holding_registers(ZERO_TYPE_REGISTER, count=1,
                                                          device_id=UNIT)
        assert not answer.isError(), answer
        return int(answer.registers[0])

    def retained(self) -> dict[str, Any] | None:
        last = self.mqtt.last(f"imu/{GID}/ah/settings")
        return None if last is None else dict(json.loads(last.payload))

    def shows(self, zero_type: str | None) -> Callable[[], Awaitable[bool]]:
        """All three show ``zero_type`` (None: unknown)."""
        code = {None: UNKNOWN, "absolute": 0, "relative": 1}[zero_type]

        async def check() -> bool:
            rest = (await self.rest())["settings"].get("zero_type")
            mqtt = (self.retained() or {}).get("zero_type")
            return rest == mqtt == zero_type and await self.register() == code
        return check

    async def status(self) -> str:
        return str((await self.rest())["status"])


async def _set_relative(clients: Clients, sensor: SimSensor) -> None:
    response = await clients.http.post("/api/v1/sensors/ah/commands/set_zero_type",
                                       json={"type": "relative"})
    assert response.json()["ok"], response.text
    assert sensor.settings.zero_type == "relative"
    await until(clients.shows("relative"))


def _power_cut(sim: SimulatorThread, sensor: SimSensor) -> None:
    """What a power cut does to the simulated sensor: back to its saved settings (the
    zero type was never saved).  Run on the simulator's loop while it is silent."""
    sim.call(sensor.apply_zero_type, "absolute", 0.0)


def _no_overlap(sim: SimulatorThread) -> None:
    assert sim.bus.stats.masters_overlaps == 0, sim.bus.stats.incidents
    assert sim.bus.stats.internal_errors == 0


async def _with_clients(sim_port: str, protocol: str, sensor: SimSensor, tmp_path: Path,
                        body: Callable[[Clients], Awaitable[None]]) -> None:
    with Mosquitto(tmp_path) as broker, recording(broker, f"imu/{GID}/#") as mqtt:
        async with running(_config(sim_port, protocol, sensor.address, broker)) as gateway:
            assert gateway.http is not None and gateway.modbus is not None
            modbus = AsyncModbusTcpClient("127.0.0.1", port=gateway.modbus.port, timeout=5,
                                          retries=0)
            assert await modbus.connect()
            try:
                async with httpx.AsyncClient(
                        base_url=f"http://127.0.0.1:{gateway.http.port}", timeout=10,
                        headers={"Authorization": f"Bearer {TOKEN}"}) as http:
                    clients = Clients(gateway, http, modbus, mqtt)
                    await until(lambda: gateway.cache.snapshot("ah").seq >= 3)
                    await body(clients)
            finally:
                modbus.close()


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", [WireProtocol.NATIVE, WireProtocol.MODBUS])
async def test_power_cycled_sensor_shows_unknown_then_what_it_says(
        tmp_path: Path, protocol: WireProtocol) -> None:
    sensor = make_sensor(protocol, Series.AH, baud=FAST)
    with simulated([sensor]) as sim:
        async def body(clients: Clients) -> None:
            await _set_relative(clients, sensor)
            sensor.faults.stalled = True  # the power is cut
            await until(lambda: clients.gateway.cache.snapshot("ah").online is False, 20)
            _power_cut(sim, sensor)
            await until(clients.shows(None))
            assert await clients.status() == "offline"
            assert clients.retained() == {}
            sensor.faults.stalled = False  # the power is back: the bus reads it anew
            await until(clients.shows("absolute"), 20)
            assert await clients.status() == "ok"

        await _with_clients(sim.path, protocol.name.lower(), sensor, tmp_path, body)
        _no_overlap(sim)


@pytest.mark.anyio
async def test_port_loss_shows_unknown_then_what_the_sensor_says(tmp_path: Path) -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST)
    link = str(tmp_path / "ttyUSB-settings")
    with simulated([sensor], link=link) as sim:
        async def body(clients: Clients) -> None:
            await _set_relative(clients, sensor)
            sim.call(sim.bus.unplug)  # the USB adapter, which powers the sensor, is pulled
            await until(lambda: not clients.gateway.masters["line"].port_open)
            _power_cut(sim, sensor)
            await until(clients.shows(None))
            sim.call(sim.bus.replug)
            await until(clients.shows("absolute"), 20)
            assert await clients.status() == "ok"

        await _with_clients(link, "native", sensor, tmp_path, body)
        _no_overlap(sim)
