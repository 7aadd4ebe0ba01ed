"""Alarms over MQTT (docs/mqtt.md, "Alarms"; docs/alarms.md), end to end: a real
mosquitto, the gateway in-process on a simulated AH that the test leans
(``sensor.lean``), and paho clients that listen, acknowledge, and try to acknowledge
without the rights.

* the alarm's retained state at start, raised by the lean after its on-delay, held
  through the hysteresis, cleared below it, the Home Assistant entities that show it;
* acknowledging over MQTT (the result, the journal's ``by``), and what is refused:
  a bad ``by``, an unknown alarm, nothing to acknowledge, a retained or empty message;
* a peer acknowledging when ``allow_commands`` is off: nothing happens;
* an alarm that leaves the config: its state and discovery configs are swept.

Waits are for events (messages, the cache's sequence numbers), never a fixed time."""

from __future__ import annotations

import asyncio
import json
import time
from datetime import datetime
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest
from support.broker import Mosquitto, Received, Recorder, recording
from support.harness import running, until

from imu_gateway.app import Gateway
from imu_gateway.derived import values_of
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, SimulatorThread, make_sensor, simulated

FAST = 115200
GID = "cranes"
BASE = f"imu/{GID}"
ON_DELAY = 0.3
LEAN = f"{BASE}/boom/alarm/boom_lean"
ACK = f"{LEAN}/ack"
BOOM_LEAN = {"name": "boom_lean", "field": "tilt", "above": 5.0, "hysteresis": 0.5,
             "on_delay_s": ON_DELAY, "severity": "critical"}
HA = "homeassistant"


def _config(line: str, broker: Mosquitto, alarms: list[dict[str, Any]],
            **mqtt: Any) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": line, "baudrate": FAST, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "alarms": alarms}]}],
            "mqtt": {"url": broker.url, "homeassistant_discovery": True, **mqtt}}


def _json(message: Received | None) -> dict[str, Any]:
    assert message is not None
    value = json.loads(message.payload)
    assert isinstance(value, dict)
    return value


def _states(rec: Recorder, topic: str = LEAN) -> list[str]:
    return [json.loads(m.payload)["state"] for m in rec.on(topic) if m.payload]


def _lean(line: SimulatorThread, sim: SimSensor, pitch: float) -> None:
    line.call(sim.lean, pitch, 0.0).result(5)


async def _tilt_is(gateway: Gateway, tilt: float, samples: int = 3) -> None:
    """Wait until the boom's tilt reads ``tilt``, then ``samples`` more samples (each
    evaluated by the alarms as it entered the cache)."""
    await until(lambda: values_of(gateway.cache.snapshot("boom")).get("tilt") == tilt)
    seq = gateway.cache.snapshot("boom").seq
    await until(lambda: gateway.cache.snapshot("boom").seq >= seq + samples)


def _written(gateway: Gateway) -> bool:
    mqtt = gateway.mqtt
    return mqtt is not None and mqtt.connected and not mqtt.outbox and \
        mqtt.stats()["in_flight"] == 0


def _retained(broker: Mosquitto, topic: str) -> dict[str, bytes]:
    """The retained messages a new subscriber to ``topic`` gets (a round trip of a
    marker at QoS 1 proves they are all in)."""
    with recording(broker, topic) as fresh:
        marker = f"{BASE}/_marker"
        fresh.client.subscribe(marker, qos=1)
        fresh.client.publish(marker, b"x", qos=1)
        fresh.wait(lambda: fresh.on(marker))
        return {m.topic: m.payload for m in fresh.messages if m.retain and m.payload}


async def _ask(rec: Recorder, payload: str, topic: str = ACK, naming: str = "",
               retain: bool = False) -> dict[str, Any]:
    """The result of one acknowledgement on ``topic``: the first new one on its result
    topic whose text has ``naming`` in it."""
    result = f"{topic}/result"
    before = len(rec.on(result))

    def found() -> list[Received]:
        return [m for m in rec.on(result)[before:] if naming in m.text]

    rec.client.publish(topic, payload, qos=1, retain=retain)
    await until(lambda: bool(found()), timeout=30)
    return _json(found()[0])


async def _refused(rec: Recorder, gateway: Gateway) -> None:
    """What is refused, and leaves the alarm unacknowledged."""
    mqtt = gateway.mqtt
    assert mqtt is not None
    bad = await _ask(rec, '{"by": ""}')
    assert (bad["ok"], bad["kind"]) == (False, "bad_arguments") and "by" in bad["error"]
    odd = await _ask(rec, '{"who": "x"}')
    assert odd["kind"] == "bad_arguments" and "'who'" in odd["error"]
    unknown = await _ask(rec, "{}", f"{BASE}/boom/alarm/nope/ack")
    assert (unknown["ok"], unknown["kind"], unknown["alarm"]) == \
        (False, "unknown_alarm", "nope")
    nobody = await _ask(rec, "{}", f"{BASE}/nobody/alarm/boom_lean/ack")
    assert nobody["kind"] == "unknown_sensor"
    ignored = mqtt.counters.ignored
    rec.client.publish(ACK, "{}", qos=1, retain=True)  # cleared, never run
    await until(lambda: mqtt.counters.ignored == ignored + 1)
    await until(lambda: any(not m.payload for m in rec.on(ACK)))  # the clearing
    rec.client.publish(ACK, "", qos=1)
    await until(lambda: mqtt.counters.ignored == ignored + 2)
    assert _states(rec)[-1] == "active_unacked"
    assert [t.by for t in gateway.alarm_journal()] == [None]


@pytest.fixture
def boom() -> Any:
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST)
    with simulated([sim]) as line:
        _lean(line, sim, 1.0)
        yield sim, line


@pytest.mark.anyio
async def test_a_lean_raises_the_alarm_on_mqtt_and_an_ack_over_mqtt_acknowledges_it(
        tmp_path: Path, boom: tuple[SimSensor, SimulatorThread]) -> None:
    sim, line = boom
    with Mosquitto(tmp_path) as broker, \
            recording(broker, f"{BASE}/#", f"{HA}/#", version=paho.MQTTv5) as rec:
        cfg = _config(line.path, broker, [BOOM_LEAN], allow_commands=True, protocol="5")
        async with running(cfg) as gateway:
            mqtt = gateway.mqtt
            assert mqtt is not None
            await until(lambda: mqtt.taking_commands)
            await _tilt_is(gateway, 1.0)
            await until(lambda: bool(_states(rec)) and
                        bool(_states(rec, f"{BASE}/boom/alarm/communication")))
            assert _json(rec.last(LEAN)) == {
                "sensor": "boom", "alarm": "boom_lean", "field": "tilt",
                "severity": "critical", "state": "normal", "active": False, "acked": True,
                "value": None, "limit": None, "since": None, "latch": False}

            # Home Assistant: a problem binary sensor per alarm, an acknowledge button
            oid = f"{GID}_boom_alarm_boom_lean"
            problem = _json(rec.last(f"{HA}/binary_sensor/{oid}/config"))
            assert (problem["device_class"], problem["state_topic"],
                    problem["json_attributes_topic"]) == ("problem", LEAN, LEAN)
            assert problem["availability_topic"] == f"{BASE}/status"
            assert _json(rec.last(f"{HA}/binary_sensor/{GID}_boom_alarm_communication/"
                                  "config"))["device_class"] == "problem"
            button = _json(rec.last(f"{HA}/button/{oid}_ack/config"))
            assert button["command_topic"] == ACK
            assert json.loads(button["payload_press"]) == {"by": "home assistant"}

            leaned_at = time.time()
            _lean(line, sim, 10.0)
            await until(lambda: "active_unacked" in _states(rec))
            raised = _json(rec.last(LEAN))
            assert (raised["value"], raised["limit"], raised["active"], raised["acked"]) == \
                (10.0, 5.0, True, False)
            # the on-delay: not active before the lean had held for it
            since = datetime.fromisoformat(raised["since"]).timestamp()
            assert since >= leaned_at + ON_DELAY - 0.002

            await _refused(rec, gateway)

            acked = await _ask(rec, '{"by": "alice", "request_id": 7}')
            assert (acked["ok"], acked["request_id"], acked["state"]["state"]) == \
                (True, 7, "active_acked")
            await until(lambda: _states(rec)[-1] == "active_acked")
            assert gateway.alarm_journal()[-1].by == "alice (mqtt)"
            again = await _ask(rec, "{}")
            assert (again["ok"], again["kind"]) == (False, "nothing_to_acknowledge")

            # back under 5 but not through the hysteresis (4.7 > 4.5): still active
            _lean(line, sim, 4.7)
            await _tilt_is(gateway, 4.7)
            assert _states(rec)[-1] == "active_acked"
            assert gateway.alarm_states()[0].state.value == "active_acked"
            _lean(line, sim, 4.0)
            await until(lambda: _states(rec)[-1] == "normal")
            assert _json(rec.last(LEAN))["value"] == 4.0
            # one message at start, then one per transition
            assert _states(rec) == ["normal", "active_unacked", "active_acked", "normal"]
            await until(lambda: _written(gateway))
            kept = await asyncio.to_thread(_retained, broker, f"{BASE}/boom/alarm/#")
        assert set(kept) == {LEAN, f"{BASE}/boom/alarm/communication"}
        assert json.loads(kept[LEAN])["state"] == "normal"
        assert [(t.from_state.value, t.to_state.value, t.by) for t in
                gateway.alarm_journal()] == [("normal", "active_unacked", None),
                                             ("active_unacked", "active_acked", "alice (mqtt)"),
                                             ("active_acked", "normal", None)]


@pytest.mark.anyio
async def test_without_allow_commands_a_peer_cannot_acknowledge(
        tmp_path: Path, boom: tuple[SimSensor, SimulatorThread]) -> None:
    sim, line = boom
    with Mosquitto(tmp_path) as broker, \
            recording(broker, f"{BASE}/#", f"{HA}/#") as rec:
        async with running(_config(line.path, broker, [BOOM_LEAN])) as gateway:
            mqtt = gateway.mqtt
            assert mqtt is not None
            await _tilt_is(gateway, 1.0)
            await until(lambda: bool(_states(rec)))
            assert rec.on(f"{HA}/button/{GID}_boom_alarm_boom_lean_ack/config") == []
            _lean(line, sim, 10.0)
            await until(lambda: "active_unacked" in _states(rec))

            # the peer tries, every way it can; the broker takes each (QoS 1) and passes
            # it on to its subscribers (the recorder sees it come back)
            for payload in ("{}", '{"by": "mallory"}', ""):
                rec.client.publish(ACK, payload, qos=1).wait_for_publish(10)
            rec.client.publish(ACK, "{}", qos=1, retain=True).wait_for_publish(10)
            await until(lambda: len(rec.on(ACK)) == 4)
            # then the lean ends: unacknowledged, the alarm returns to rtn_unacked (an
            # acknowledged one would go to normal)
            _lean(line, sim, 4.0)
            await until(lambda: _states(rec)[-1] == "rtn_unacked")
            assert [t.by for t in gateway.alarm_journal()] == [None, None]
            assert mqtt.counters.commands == 0 and mqtt.counters.ignored == 0
            assert rec.on(f"{ACK}/result") == []
            # the peer's retained message is not the gateway's to clear
            assert rec.last(ACK) is not None and rec.last(ACK).payload == b"{}"  # type: ignore[union-attr]


@pytest.mark.anyio
async def test_an_alarm_that_leaves_the_config_is_swept(
        tmp_path: Path, boom: tuple[SimSensor, SimulatorThread]) -> None:
    _, line = boom
    old = {"name": "old_one", "field": "pitch", "below": -45.0}
    with Mosquitto(tmp_path) as broker:
        cfg = _config(line.path, broker, [BOOM_LEAN, old], allow_commands=True)
        async with running(cfg) as gateway:
            await _tilt_is(gateway, 1.0)
            await until(lambda: _written(gateway))
            before = await asyncio.to_thread(_retained, broker, "#")
        gone = {f"{BASE}/boom/alarm/old_one",
                f"{HA}/binary_sensor/{GID}_boom_alarm_old_one/config",
                f"{HA}/button/{GID}_boom_alarm_old_one_ack/config"}
        assert gone <= set(before)
        assert json.loads(before[f"{BASE}/boom/alarm/old_one"])["state"] == "normal"

        cfg["buses"][0]["sensors"][0]["alarms"] = [BOOM_LEAN]
        async with running(cfg) as gateway:
            mqtt = gateway.mqtt
            assert mqtt is not None
            await until(lambda: mqtt.sweep.cleared >= len(gone), timeout=20)
            await until(lambda: _written(gateway))
            assert mqtt.sweep.cleared == len(gone)
            after = await asyncio.to_thread(_retained, broker, "#")
        assert set(after) == set(before) - gone
