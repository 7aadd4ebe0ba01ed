"""MQTT's own reads of the cache, outside its events (a deferred send at the end of
``min_interval_ms``, the announcement after a connect), show what it has heard: a
turn the buses handed over and the loop has not run yet is not applied inside them
(``Cache.heard``).  Applied there, it told MQTT the reading inside its own call, and
MQTT sent that state twice.  Each state goes once, in order.

The bus thread's side is played as in ``test_lazy_hand_over``: a turn handed over
waits in the writer until the loop runs (``await asyncio.sleep(0)``)."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest

from imu_gateway.app import Gateway
from imu_gateway.bus.runner import CacheWriter
from imu_gateway.config import config_from_dict
from imu_gateway.frontends.mqtt.states import StateDesk
from imu_gateway.frontends.mqtt.topics import Topics
from imu_gateway.model import Angles, Reading
from imu_gateway.mqtt_link.message import Message


def reading(pitch: float) -> Reading:
    return Reading(angles=Angles(pitch, 0.0, 0.0))


def desk(**mqtt: Any) -> tuple[Gateway, StateDesk, CacheWriter, list[Message]]:
    """A gateway (never started) and its MQTT state desk, connected, sending into a
    list; the desk listens to the cache as the MQTT client does (prompt)."""
    gw = Gateway(config_from_dict({
        "gateway_id": "heard", "mqtt": {"url": "mqtt://127.0.0.1:1", **mqtt},
        "buses": [{"name": "line", "port": "/dev/null", "protocol": "native",
                   "sensors": [{"name": "boom", "series": "AH", "address": 0}]}]}, env={}))
    assert gw.config.mqtt is not None
    sent: list[Message] = []
    states = StateDesk(gw, gw.config.mqtt, Topics.of(gw.config.mqtt, "heard"), sent.append,
                       sent.append, lambda: True, lambda: [])
    gw.cache.subscribe(states.on_cache_event)
    writer = CacheWriter(gw.cache)
    writer.loop = asyncio.get_running_loop()
    return gw, states, writer, sent


def state_seqs(sent: list[Message]) -> list[int]:
    return [json.loads(m.payload)["seq"] for m in sent if m.topic.endswith("/boom/state")]


def hand_over(writer: CacheWriter, pitch: float) -> None:
    """One turn of the bus loop that read the sensor: handed over, not run yet."""
    writer.publish("boom", reading(pitch))
    writer.flush()


@pytest.mark.anyio
async def test_a_deferred_send_sends_what_was_heard_and_each_state_once() -> None:
    gw, states, writer, sent = desk(min_interval_ms=60_000)
    gw.cache.publish("boom", reading(1.0))  # sent at once
    gw.cache.publish("boom", reading(2.0))  # within the interval: deferred
    hand_over(writer, 3.0)  # waiting for the loop when the deferred send comes
    out = states._sensors["boom"]
    assert out.trailing is not None
    out.trailing.cancel()
    states._send_trailing("boom")  # (its timer, brought forward)
    await asyncio.sleep(0)  # the loop runs the hand-over: 3 is heard, and deferred
    assert out.trailing is not None
    out.trailing.cancel()
    states._send_trailing("boom")
    assert state_seqs(sent) == [1, 2, 3]


@pytest.mark.anyio
async def test_an_announcement_sends_what_was_heard_and_each_state_once() -> None:
    gw, states, writer, sent = desk()
    gw.cache.publish("boom", reading(1.0))
    hand_over(writer, 2.0)
    sent.clear()
    states.announce()  # a reconnect, with a turn waiting for the loop
    await asyncio.sleep(0)
    assert state_seqs(sent) == [1, 2]
