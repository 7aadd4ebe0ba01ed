"""The topics Home Assistant's entities read, on a real mosquitto: the throttled state
topic, the settings the select and number entities show (changed by a command sent
the way Home Assistant sends it), the diagnostics, and a stalled sensor's state
turning unavailable at once."""

from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from support.broker import Mosquitto, Received, recording
from support.harness import running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "gw"
BASE = f"imu/{GID}"
FAST = 115200
HA_INTERVAL_MS = 400


def _config(line: str, broker: Mosquitto) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": line, "baudrate": FAST, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "mins", "series": "MINS", "stream_hz": 100},
                                   {"name": "ah", "series": "AH", "address": 1,
                                    "poll_hz": 20}]}],
            "mqtt": {"url": broker.url, "homeassistant_discovery": True,
                     "homeassistant_min_interval_ms": HA_INTERVAL_MS,
                     "allow_commands": True}}


def _seconds(ts: str) -> float:
    return datetime.fromisoformat(ts.replace("Z", "+00:00")).timestamp()


def _json(messages: list[Received]) -> list[dict[str, Any]]:
    return [json.loads(m.payload) for m in messages]


@pytest.mark.anyio
async def test_home_assistant_topics(tmp_path: Path) -> None:
    mins = make_sensor(WireProtocol.NATIVE, Series.MINS, 0, baud=FAST,
                       source=Motion.from_seed(3))
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 1, baud=FAST, source=Motion.from_seed(4))
    with Mosquitto(tmp_path) as broker, simulated([mins, ah]) as line, \
            recording(broker, f"{BASE}/#", "homeassistant/#") as rec:
        async with running(_config(line.path, broker)) as gateway:
            await until(lambda: len(rec.on(f"{BASE}/mins/state")) >= 300, timeout=30)

            # the throttle: Home Assistant's topic at most once per interval, while
            # the state topic carries every reading (counted over the span of the
            # samples' own times, not of their arrival)
            states, ha = _json(rec.on(f"{BASE}/mins/state")), _json(rec.on(f"{BASE}/mins/ha"))
            span = (_seconds(states[-1]["ts"]) - _seconds(states[0]["ts"]))
            assert 1 <= len(ha) <= span / (HA_INTERVAL_MS / 1000) + 3, (len(ha), span)
            assert len(states) > 5 * len(ha)

            # a command as Home Assistant's select sends it: its command template
            select = json.loads(rec.on(
                f"homeassistant/select/{GID}_ah_set_zero_type/config")[-1].payload)
            payload = select["command_template"].replace("{{ value | tojson }}",
                                                         json.dumps("relative"))
            rec.client.publish(select["command_topic"], payload, qos=1)
            await until(lambda: any(s.get("zero_type") == "relative"
                                    for s in _json(rec.on(select["state_topic"]))))
            assert ah.settings.zero_type == "relative"

            # the diagnostics the gateway's and the sensors' diagnostic entities read
            await until(lambda: bool(rec.on(f"{BASE}/diagnostics")))
            diagnostics = _json(rec.on(f"{BASE}/diagnostics"))[-1]
            assert diagnostics["buses"]["a"]["transactions_per_s"] >= 0
            assert set(diagnostics["sensors"]) == {"mins", "ah"}
            for config in (json.loads(m.payload) for m in rec.messages
                           if m.topic.startswith("homeassistant/")):
                read = config.get("state_topic") or config["command_topic"]
                assert read.startswith(f"{BASE}/")

            # a stalled sensor: its Home Assistant state says so at once (unavailable)
            ah.faults.stalled = True
            # (on a busy machine the stall may come before the sensor's first state)
            await until(lambda: any(s["status"] != "ok" for s in
                                    _json(rec.on(f"{BASE}/ah/ha"))[-1:]), timeout=20)
            assert gateway.cache.snapshot("ah").status.value != "ok"
