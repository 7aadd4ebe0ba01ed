"""MQTT commands from the side of a peer trying to misuse them (docs/mqtt.md,
"Commands"): a response topic that would make the gateway speak on topics others trust
(a confused deputy), and arguments with a key given twice.

A real mosquitto (``broker.Mosquitto``), the gateway in-process on a simulated sensor,
and a paho MQTT 5 client that asks and listens.  Expected words come from docs/mqtt.md.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from support.broker import Mosquitto, Received, Recorder, recording
from support.harness import running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
GID = "deputy"
BASE = f"imu/{GID}"
CMD = f"{BASE}/boom/cmd"
#: Response topics a peer may not have results published on, and what the refusal says.
FORBIDDEN = {
    f"{BASE}/boom/state": "under imu/",  # the confused deputy of the issue
    f"{BASE}/boom/cmd/save": "under imu/",  # a command of the gateway's own
    "imu/another-gateway/status": "under imu/",
    "homeassistant/sensor/boom/config": "under homeassistant/",
    "spBv1.0/plant/NCMD/edge": "under spBv1.0/",
    "$SYS/broker/uptime": "$ topic",
    "$share/g/x": "$ topic",
}
ALLOWED = (f"{BASE}/replies/me/1", f"{BASE}/replies", "replies/me")


def _properties(response_topic: str, correlation: bytes) -> Properties:
    props = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
    props.ResponseTopic = response_topic
    props.CorrelationData = correlation
    return props


def _result(message: Any) -> dict[str, Any]:
    value = json.loads(message.payload)
    assert isinstance(value, dict)
    return value


async def _ask(rec: Recorder, topic: str, payload: str, result_topic: str,
               properties: Properties | None = None, naming: str = "") -> dict[str, Any]:
    """The result of one command: the first one on ``result_topic`` after it was sent
    whose text has ``naming`` in it.  (QoS 1 lets a broker deliver an earlier result
    again, seen under CPU load: the next one to come is not always this one's.)"""
    before = len(rec.on(result_topic))

    def found() -> list[Received]:
        return [m for m in rec.on(result_topic)[before:] if naming in m.text]

    rec.client.publish(topic, payload, qos=1, properties=properties)
    await until(lambda: bool(found()), timeout=30)
    return _result(found()[0])


@pytest.mark.anyio
async def test_results_on_topics_others_trust_are_refused_and_said_so(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST,
                      source=hold(Motion.from_seed(3).sample(10.0)))
    listened = [f"{CMD}/+/result", f"{BASE}/#", "homeassistant/#", "spBv1.0/#",
                "replies/#"]
    with Mosquitto(tmp_path) as broker, simulated([sim]) as line, \
            recording(broker, *listened, version=paho.MQTTv5) as rec:
        cfg = {"gateway_id": GID,
               "buses": [{"name": "a", "port": line.path, "baudrate": FAST,
                          "protocol": "native", "sensors": [{"name": "boom", "series": "AH"}]}],
               "mqtt": {"url": broker.url, "protocol": "5", "allow_commands": True,
                        "homeassistant_discovery": True}}
        async with running(cfg) as gateway:
            await until(lambda: gateway.mqtt is not None and gateway.mqtt.taking_commands)
            caplog.clear()
            with caplog.at_level(logging.WARNING):
                for n, (topic, says) in enumerate(FORBIDDEN.items()):
                    result = await _ask(rec, f"{CMD}/read_settings", "{}",
                                        f"{CMD}/read_settings/result",
                                        _properties(topic, b"no-%d" % n),
                                        naming=json.dumps(f"the response topic {topic!r}")[1:-1])
                    assert result["ok"] is False and result["kind"] == "bad_arguments"
                    assert f"the response topic {topic!r}" in result["error"], result
                    assert says in result["error"], result
                    assert "ask for results on imu/deputy/replies/" in result["error"] \
                        or says == "$ topic", result
            # Logged once, with the cause; the others in the minute are counted.
            refusals = [r.getMessage() for r in caplog.records if "was not run" in r.getMessage()]
            assert len(refusals) == 1, refusals
            assert "state" in refusals[0] and "under imu/" in refusals[0]

            # The replies subtree, and topics outside the gateway's, get their result.
            for n, topic in enumerate(ALLOWED):
                result = await _ask(rec, f"{CMD}/read_settings", "{}", topic,
                                    _properties(topic, b"yes-%d" % n))
                assert result["ok"] is True, result
                assert rec.on(topic)[-1].properties.CorrelationData == b"yes-%d" % n

        # Nothing the peer asked for came on the topics it was refused (they came in
        # order before the allowed ones).  A result carries its request's correlation
        # data: only the requests themselves carry the refused ones'.
        for message in rec.messages:
            correlation = getattr(message.properties, "CorrelationData", b"")
            if correlation.startswith(b"no-"):
                assert message.topic == f"{CMD}/read_settings", message
            if message.topic in FORBIDDEN:
                assert b'"command"' not in message.payload, message


@pytest.mark.anyio
async def test_a_key_given_twice_is_refused_naming_it(tmp_path: Path) -> None:
    """``{"type": "absolute", "type": "relative"}`` used to run as relative."""
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, baud=FAST,
                      source=hold(Motion.from_seed(3).sample(10.0)))
    with Mosquitto(tmp_path) as broker, simulated([sim]) as line, \
            recording(broker, f"{CMD}/+/result") as rec:
        cfg = {"gateway_id": GID,
               "buses": [{"name": "a", "port": line.path, "baudrate": FAST,
                          "protocol": "native", "sensors": [{"name": "boom", "series": "AH"}]}],
               "mqtt": {"url": broker.url, "allow_commands": True}}
        async with running(cfg) as gateway:
            await until(lambda: gateway.mqtt is not None and gateway.mqtt.taking_commands)
            zero_type = sim.settings.zero_type
            for payload, key in (('{"type": "absolute", "type": "relative"}', "type"),
                                 ('{"type": "relative", "request_id": 1, "request_id": 2}',
                                  "request_id")):
                result = await _ask(rec, f"{CMD}/set_zero_type", payload,
                                    f"{CMD}/set_zero_type/result")
                assert result["ok"] is False and result["kind"] == "bad_arguments"
                assert result["error"] == f"the key '{key}' is given twice; give each key once"
            assert sim.settings.zero_type == zero_type
            result = await _ask(rec, f"{CMD}/set_zero_type", '{"type": "relative"}',
                                f"{CMD}/set_zero_type/result")
            assert result["ok"] is True
