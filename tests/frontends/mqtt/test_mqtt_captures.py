"""MQTT announces each new capture (docs/mqtt.md, "Captures") on a real mosquitto:
``{base}/{gateway_id}/captures``, JSON, not retained."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.broker import Mosquitto, recording
from support.harness import running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

TOPIC = "imu/cap/captures"


@pytest.mark.anyio
async def test_each_new_capture_is_announced_not_retained(tmp_path: Path) -> None:
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, baud=115200)
    folder = tmp_path / "captures"
    with Mosquitto(tmp_path) as broker, simulated([sim]) as line, \
            recording(broker, TOPIC) as rec:
        config = {"gateway_id": "cap", "mqtt": {"url": broker.url},
                  "capture": {"dir": str(folder), "pre_s": 0.5, "post_s": 0},
                  "buses": [{"name": "a", "port": line.path, "baudrate": 115200,
                             "protocol": "native",
                             "sensors": [{"name": "boom", "series": "AH"}]}]}
        async with running(config) as gateway:
            assert gateway.mqtt is not None and gateway.captures is not None
            await until(lambda: gateway.mqtt is not None and gateway.mqtt.connected)
            await until(lambda: gateway.cache.snapshot("boom").seq >= 3)
            first = gateway.captures.trigger("manual")
            await until(lambda: len(rec.on(TOPIC)) == 1)
            second = gateway.captures.trigger("alarm", alarm="boom/boom_lean")
            await until(lambda: len(rec.on(TOPIC)) == 2)
        announced = [json.loads(m.payload) for m in rec.on(TOPIC)]
        assert [a["id"] for a in announced] == [first, second]
        assert announced[1]["trigger"] == "alarm" and announced[1]["alarm"] == "boom/boom_lean"
        for a in announced:
            assert set(a) == {"id", "trigger", "alarm", "time", "size"}
            assert a["size"] == (folder / f"{a['id']}.zip").stat().st_size
            assert a["time"].endswith("Z")
        assert not any(m.retain for m in rec.on(TOPIC))
        # and a subscriber that comes later finds none kept
        with recording(broker, TOPIC) as fresh:
            marker = "imu/cap/_marker"  # (a round trip: the retained ones came before it)
            fresh.client.subscribe(marker, qos=1)
            fresh.client.publish(marker, b"x", qos=1)
            fresh.wait(lambda: fresh.on(marker))
            assert fresh.on(TOPIC) == []
