"""After the broker was away, a state topic gets each sensor's latest state once, then
live ones: never a replayed burst of old states, never a duplicate, and ``ts`` never
goes backwards.  With ``mqtt.backfill`` the missed states come on the history topic,
with their own ``ts``, paced.

A real mosquitto is restarted under a 100 Hz stream.  The gateway reaches it through a
gate the test holds shut until the recording subscriber (straight to the broker) is
back, so that the subscriber sees everything the gateway sends after the restart.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest
from support.broker import Gate, Mosquitto, Received, recording
from support.harness import running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "gw"
BASE = f"imu/{GID}"
FAST = 115200


def _gateway(line: str, port: int, **mqtt: Any) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": line, "baudrate": FAST, "protocol": "native",
                       "sensors": [{"name": "mins", "series": "MINS", "stream_hz": 100},
                                   {"name": "ah", "series": "AH", "address": 1,
                                    "poll_hz": 20}]}],
            "mqtt": {"url": f"mqtt://127.0.0.1:{port}", **mqtt}}


def _states(messages: list[Received], leaf: str) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = {}
    for m in messages:
        parts = m.topic.split("/")
        if len(parts) == 4 and parts[3] == leaf:
            out.setdefault(parts[2], []).append(json.loads(m.payload))
    return out


async def _restart_under_stream(tmp_path: Path, **mqtt: Any) -> tuple[
        list[Received], dict[str, int], dict[str, int], Any]:
    """Runs the gateway, restarts the broker for 2 s of readings, and returns what the
    subscriber got after the restart, each sensor's seq when the gate closed and when
    it opened, and the gateway's MQTT counters."""
    sensors = [make_sensor(WireProtocol.NATIVE, Series.MINS, 0, baud=FAST,
                           source=Motion.from_seed(1)),
               make_sensor(WireProtocol.NATIVE, Series.AH, 1, baud=FAST,
                           source=Motion.from_seed(2))]
    with Mosquitto(tmp_path) as broker, simulated(sensors) as line, \
            recording(broker, f"{BASE}/+/state", f"{BASE}/+/history") as rec:
        async with Gate(broker.port) as gate, \
                running(_gateway(line.path, gate.port, **mqtt)) as gateway:
            mqtt_client = gateway.mqtt
            assert mqtt_client is not None
            await until(lambda: gateway.cache.snapshot("mins").streaming)
            await until(lambda: len(rec.on(f"{BASE}/mins/state")) > 100)
            gate.cut()
            broker.stop()
            await until(lambda: not mqtt_client.connected)
            closed = {n: gateway.cache.snapshot(n).seq for n in ("mins", "ah")}
            await until(lambda: gateway.cache.snapshot("mins").seq > closed["mins"] + 200)
            broker.start()  # the same port; it remembers nothing
            await until(lambda: rec.client.is_connected(), timeout=20)
            await asyncio.to_thread(_resubscribed, rec)
            after = len(rec.messages)
            opened = {n: gateway.cache.snapshot(n).seq for n in ("mins", "ah")}
            gate.shut = False
            await until(lambda: mqtt_client.stats()["connects"] == 2, timeout=30)
            await until(lambda: len(rec.messages) > after + 100)
            if mqtt.get("backfill"):
                await until(lambda: mqtt_client.states.backfill is not None
                            and not mqtt_client.states.backfill.kept, timeout=60)
            return rec.messages[after:], closed, opened, mqtt_client.stats()


def _resubscribed(rec: Any) -> None:
    """The recorder's subscriptions are back: a message of its own comes through."""
    probe = f"{BASE}/probe/state"
    rec.client.publish(probe, json.dumps({"probe": True}), qos=1)
    rec.wait(lambda: rec.on(probe), timeout=20)


def _check_state_topics(states: dict[str, list[dict[str, Any]]],
                        opened: dict[str, int]) -> None:
    for name in ("mins", "ah"):
        got = states[name]
        # the first is the latest there was when the gateway came back: no old one
        assert got[0]["seq"] >= opened[name], (name, got[0]["seq"], opened[name])
        seqs = [s["seq"] for s in got]
        assert seqs == sorted(seqs), f"{name}: a step back"
        # (a status change sends the reading again with its new status: on a busy
        # machine a 20 Hz sensor can go stale and back; the same seq with another
        # status is no duplicate)
        sent = [(s["seq"], s["status"]) for s in got]
        assert len(sent) == len(set(sent)), f"{name}: a duplicate {sent}"
        times = [s["ts"] for s in got]
        assert times == sorted(times), f"{name}: ts went backwards"


@pytest.mark.anyio
async def test_after_a_broker_restart_each_state_topic_gets_the_latest_once(
        tmp_path: Path) -> None:
    received, _, opened, stats = await _restart_under_stream(tmp_path)
    _check_state_topics(_states(received, "state"), opened)
    assert not _states(received, "history")  # no backfill unless asked for
    assert stats["dropped"] >= 200  # the missed states, counted


@pytest.mark.anyio
async def test_backfill_sends_the_missed_states_on_the_history_topic_paced(
        tmp_path: Path) -> None:
    received, closed, opened, _ = await _restart_under_stream(
        tmp_path, backfill=True, backfill_per_s=200, queue_size=300)
    states = _states(received, "state")
    _check_state_topics(states, opened)
    history = _states(received, "history")
    mins = [s["seq"] for s in history["mins"]]
    assert mins == sorted(set(mins))  # oldest first, each once
    # what was missed while the gateway was away (the oldest may have been dropped,
    # as queue_size says), all older than what the state topic got after it
    assert closed["mins"] - 5 <= mins[0] and mins[-1] < states["mins"][0]["seq"]
    assert len(mins) >= 150
    paced = [m.at for m in received if m.topic.endswith("/history")]
    assert paced[-1] - paced[0] >= (len(paced) - 1) / 200 * 0.8  # at most 200 a second
