"""A reload that changes the sensors, seen from a real mosquitto (docs/mqtt.md, "A
reload"): the MQTT client keeps its connection (the broker's log shows one CONNECT
from it, and its status never says offline), says the discovery configs of a sensor
added, sweeps those of a sensor removed and clears its retained topics."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path
from typing import Any

import pytest
from support.broker import Mosquitto, Recorder, recording
from support.harness import running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "gw"
BASE = f"imu/{GID}"
CLIENT_ID = f"imu-gateway-{GID}"
READING = Motion.from_seed(7).sample(2.0)
TILT = {"name": "tilt", "field": "pitch", "above": 80}


def _config(line: str, broker: Mosquitto, sensors: list[dict[str, Any]]) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": line, "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300, "sensors": sensors}],
            "mqtt": {"url": broker.url, "homeassistant_discovery": True}}


def _connects(broker: Mosquitto) -> int:
    """The CONNECTs the broker took from the gateway's client id (not its probes')."""
    return len(re.findall(rf"New client connected from \S+ as {re.escape(CLIENT_ID)} \(",
                          broker.log.read_text()))


def _retained(broker: Mosquitto, *topics: str) -> dict[str, bytes]:
    """What the broker serves retained now, to a subscriber that comes after."""
    with recording(broker, *topics, "test/marker") as fresh:
        # the broker sends the retained ones as it takes each SUBSCRIBE; a marker
        # published after them on the same connection comes behind them all
        fresh.client.publish("test/marker", b"x", qos=1)
        fresh.wait(lambda: fresh.on("test/marker"))
        return {m.topic: m.payload for m in fresh.messages if m.retain}


def _discovery_of(sensor: str, messages: dict[str, bytes]) -> set[str]:
    return {t for t, p in messages.items()
            if t.startswith("homeassistant/") and f"_{sensor}_" in t and p}


async def _start(rec: Recorder, broker: Mosquitto) -> None:
    await until(lambda: any(m.payload == b"online" for m in rec.on(f"{BASE}/status"))
                and _connects(broker) == 1, timeout=20)
    await until(lambda: bool(rec.on(f"{BASE}/boom/state")), timeout=20)


def _emptied(rec: Recorder, topic: str) -> bool:
    last = rec.last(topic)
    return last is not None and last.payload == b""


def _offline_said(rec: Recorder) -> bool:
    return any(m.payload == b"offline" for m in rec.on(f"{BASE}/status"))


@pytest.mark.anyio
async def test_a_sensor_added_is_announced_on_the_same_connection(tmp_path: Path) -> None:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    arm = make_sensor(WireProtocol.NATIVE, Series.AH, 1, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([boom, arm]) as line, \
            recording(broker, f"{BASE}/#", "homeassistant/#") as rec:
        first = _config(line.path, broker, [{"name": "boom", "series": "AH"}])
        async with running(first) as gw:
            await _start(rec, broker)
            assert not _discovery_of("arm", _retained(broker, "homeassistant/#"))
            second = copy.deepcopy(first)
            second["buses"][0]["sensors"].append(
                {"name": "arm", "series": "AH", "address": 1, "alarms": [TILT]})
            outcome = await gw.reloader.put(second, dry_run=False)
            assert outcome.applied
            await until(lambda: bool(rec.on(f"{BASE}/arm/state")), timeout=20)
            await until(lambda: any(json.loads(m.payload).get("status") == "ok"
                                    for m in rec.on(f"{BASE}/arm/ha")), timeout=20)
            served = _retained(broker, "homeassistant/#", f"{BASE}/#")
            configs = _discovery_of("arm", served)
            # its measured values, its diagnostics, its alarms (tilt, communication)
            assert f"homeassistant/sensor/{GID}_arm_pitch/config" in configs
            assert f"homeassistant/binary_sensor/{GID}_arm_alarm_tilt/config" in configs
            assert served[f"{BASE}/arm/availability"] == b"online"
            assert json.loads(served[f"{BASE}/arm/alarm/tilt"])["alarm"] == "tilt"
            assert _discovery_of("boom", served)  # the others' kept
            # the same connection: one CONNECT, and the status never said offline
            assert _connects(broker) == 1
            assert not _offline_said(rec)


@pytest.mark.anyio
async def test_a_sensor_removed_is_swept_and_a_changed_one_said_again(
        tmp_path: Path) -> None:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    arm = make_sensor(WireProtocol.NATIVE, Series.AH, 1, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([boom, arm]) as line, \
            recording(broker, f"{BASE}/#", "homeassistant/#") as rec:
        first = _config(line.path, broker, [{"name": "boom", "series": "AH"},
                                            {"name": "arm", "series": "AH", "address": 1}])
        async with running(first) as gw:
            await _start(rec, broker)
            await until(lambda: bool(rec.on(f"{BASE}/arm/state")), timeout=20)
            before = _retained(broker, "homeassistant/#", f"{BASE}/#")
            arm_configs = _discovery_of("arm", before)
            assert arm_configs and f"{BASE}/arm/state" in before
            second = copy.deepcopy(first)
            second["buses"][0]["sensors"] = [{"name": "boom", "series": "AH",
                                              "alarms": [TILT]}]
            await gw.reloader.put(second, dry_run=False)
            # each of its configs emptied, and its retained topics cleared
            await until(lambda: all(_emptied(rec, t) for t in arm_configs), timeout=20)
            await until(lambda: _emptied(rec, f"{BASE}/arm/state"))
            tilt = f"homeassistant/binary_sensor/{GID}_boom_alarm_tilt/config"
            await until(lambda: bool(rec.on(tilt)))
            served = _retained(broker, "homeassistant/#", f"{BASE}/#")
            assert not _discovery_of("arm", served)
            assert not [t for t in served if t.startswith(f"{BASE}/arm/")]
            # boom changed (an alarm more): its new entity is there, its others kept
            assert tilt in served and _discovery_of("boom", served) > {tilt}
            assert json.loads(served[f"{BASE}/boom/alarm/tilt"])["alarm"] == "tilt"
            assert _connects(broker) == 1
            assert not _offline_said(rec)
