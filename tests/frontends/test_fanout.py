"""What a sample costs the front ends (docs/benchmarks.md, "CPU per sample in the front
ends"): the work done once per sample, not once per front end or client, and none
where no client asked.  Real peers (mosquitto, SSE clients over HTTP, pymodbus, an
asyncua client); the readings are put into the cache by the test, as a bus master
would, so that the number of samples is the test's.  Each test counts the work it is
about (an encoding, a pack, a copy) and checks what the clients got."""

from __future__ import annotations

import asyncio
import copy
import functools
import math
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.server import monitored_item_service
from pymodbus.client import AsyncModbusTcpClient
from support.broker import Mosquitto, recording
from support.harness import free_port, running, until

from imu_gateway.app import Gateway
from imu_gateway.cache import Snapshot
from imu_gateway.frontends.modbus import map as modbus_map
from imu_gateway.model import VALUE_GROUPS
from imu_gateway.normalise import field_values
from imu_gateway.simulator.motion import Motion

SAMPLES = 40
FIELDS = [(f"{spec.title}.{name}", name) for spec in VALUE_GROUPS.values()
          for name in spec.fields]


def _config(**front_ends: Any) -> dict[str, Any]:
    """One AH sensor on a line that never opens: the test is its bus master."""
    return {"gateway_id": "gw",
            "buses": [{"name": "a", "port": "/dev/null-fanout", "protocol": "native",
                       "sensors": [{"name": "s0", "series": "AH", "poll_hz": 1}]}],
            **front_ends}


async def _feed(gateway: Gateway, samples: int, delivered: Callable[[int], bool]) -> None:
    """``samples`` readings, each after the one before was ``delivered`` (its seq)."""
    motion = Motion.from_seed(5)
    for n in range(samples):
        seq = gateway.cache.publish("s0", motion.sample(0.01 * n))
        await until(functools.partial(delivered, seq))


class _Counting:
    """Counts the calls of a function it wraps."""

    def __init__(self, wrapped: Callable[..., Any]) -> None:
        self.wrapped, self.calls = wrapped, 0

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls += 1
        return self.wrapped(*args, **kwargs)


class _SseClient:
    """A raw HTTP client of ``/api/v1/stream``: the ``seq`` of every reading event."""

    def __init__(self, port: int) -> None:
        self.port, self.seqs = port, list[int]()
        self.task = asyncio.create_task(self._read())

    async def _read(self) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", self.port)
        writer.write(b"GET /api/v1/stream HTTP/1.1\r\nHost: test\r\n\r\n")
        reading = False
        try:
            while line := await reader.readline():
                if line.startswith(b"event:"):
                    reading = line.startswith(b"event: reading")
                elif reading and line.startswith(b"data:"):
                    start = line.index(b'"seq":') + 6
                    self.seqs.append(int(line[start:line.index(b",", start)]))
        finally:
            writer.close()


@pytest.mark.anyio
async def test_a_sample_is_encoded_once_for_every_front_end_and_client(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """MQTT's state topic, Home Assistant's and two live-stream clients all carry the
    reading JSON: it is made once per sample (the MQTT client and the stream made a
    copy each)."""
    encode, encoded = Snapshot.to_json, [0]

    def to_json(snap: Snapshot) -> dict[str, Any]:
        encoded[0] += 1
        return encode(snap)

    monkeypatch.setattr(Snapshot, "to_json", to_json)
    http = free_port()
    with Mosquitto(tmp_path) as broker, recording(broker, "imu/gw/s0/state") as rec:
        # (Home Assistant's state throttled beyond the test's length, however slow the
        # machine: each of its sends takes a snapshot of its own)
        config = _config(mqtt={"url": broker.url, "homeassistant_discovery": True,
                               "homeassistant_min_interval_ms": 600_000},
                         http={"listen": f"127.0.0.1:{http}"})
        async with running(config) as gateway:
            assert gateway.mqtt is not None
            mqtt = gateway.mqtt
            await until(lambda: mqtt.connected)
            streams = [_SseClient(http), _SseClient(http)]
            await until(lambda: gateway.http is not None
                        and gateway.http.stats()["streams"] == 2)
            before = encoded[0]
            await _feed(gateway, SAMPLES, lambda seq: all(seq in s.seqs for s in streams)
                        and len(rec.on("imu/gw/s0/state")) >= seq)
            made = encoded[0] - before
            for stream in streams:
                stream.task.cancel()
    assert [s.seqs[-SAMPLES:] for s in streams] == [list(range(1, SAMPLES + 1))] * 2
    # one per sample, and a few for Home Assistant's first state and the first
    # reading's status change (snapshots of their own)
    assert made <= SAMPLES + 4, f"{made} encodings for {SAMPLES} samples"


@pytest.mark.anyio
async def test_modbus_packs_a_reading_only_when_a_client_reads_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """No client, no work: readings nobody reads are not packed into registers; the
    first read packs the latest, and reads what a client always read."""
    pack = _Counting(modbus_map._pack)
    monkeypatch.setattr(modbus_map, "_pack", pack)
    port = free_port()
    async with running(_config(modbus={"listen": f"127.0.0.1:{port}"})) as gateway:
        pack.calls = 0  # (the empty image, before any reading)
        await _feed(gateway, SAMPLES, lambda seq: True)
        assert pack.calls == 0, f"{pack.calls} registers packed with no client"
        latest = gateway.cache.snapshot("s0").reading
        assert latest is not None
        client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
        assert await client.connect()
        try:
            answer = await client.read_holding_registers(100, count=32, device_id=1)
        finally:
            client.close()
    assert not answer.isError(), answer
    got = [client.convert_from_registers(answer.registers[i:i + 2], client.DATATYPE.FLOAT32)
           for i in range(0, 32, 2)]
    want = field_values(latest)
    assert got == pytest.approx([want[name] for _, name in FIELDS[:16]], rel=1e-6)
    # one image: the 16 measured and 3 derived floats, and their scaled copies
    assert pack.calls == 2 * len(FIELDS) == 38


@pytest.mark.anyio
async def test_opcua_notifies_a_subscriber_without_copying_each_value(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """asyncua deep-copies every value written for each monitored item; the gateway's
    values are immutable and their own copy: no copy is made, and the subscriber gets
    every value of every sample."""
    copies = [0]

    def deepcopy(value: Any, memo: Any = None) -> Any:
        made = copy.deepcopy(value, memo)
        copies[0] += made is not value
        return made

    monkeypatch.setattr(monitored_item_service, "copy", types.SimpleNamespace(
        deepcopy=deepcopy))
    port = free_port()
    config = _config(opcua={"listen": f"127.0.0.1:{port}", "allow_none": True,
                            "pki_dir": str(tmp_path / "pki")})
    got: dict[str, list[float]] = {name: [] for _, name in FIELDS}

    class Handler:
        def __init__(self, names: dict[str, str]) -> None:
            self.names = names

        def datachange_notification(self, node: Any, value: float, data: Any) -> None:
            if not math.isnan(value):
                got[self.names[node.nodeid.Identifier]].append(value)

    async with running(config) as gateway, \
            Client(f"opc.tcp://127.0.0.1:{port}/", timeout=10) as client:
        idx = await client.get_namespace_index("urn:imu-gateway")
        ids = {f"gw.Sensors.s0.{path}": name for path, name in FIELDS}
        subscription = await client.create_subscription(10, Handler(ids))
        await subscription.subscribe_data_change(
            [client.get_node(ua.NodeId(nodeid, idx)) for nodeid in ids])
        copies[0] = 0
        sent: list[dict[str, float]] = []

        def delivered(seq: int) -> bool:
            reading = gateway.cache.snapshot("s0").reading
            assert reading is not None
            if len(sent) < seq:
                sent.append(field_values(reading))
            return all(got[name] and got[name][-1] == pytest.approx(sent[-1][name], rel=1e-6)
                       for name in got if not math.isnan(sent[-1][name]))

        await _feed(gateway, SAMPLES, delivered)
        await subscription.delete()
    assert copies[0] == 0, f"{copies[0]} values copied for {SAMPLES} samples"
