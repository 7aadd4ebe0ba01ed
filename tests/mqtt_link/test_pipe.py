"""``Pipe``'s window on its own: what is in paho's hands is counted from paho's own
``MQTTMessageInfo`` of each message (``settle``), QoS 0 ones as written, the others as
acknowledged.  paho's side is a stand-in that hands out real ``MQTTMessageInfo``s
and marks them published as paho would (``_set_as_published``: its write of a QoS 0
message, its handling of an acknowledgement): what is tested is the counting."""

from __future__ import annotations

import asyncio
import logging

import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import MQTTErrorCode

from imu_gateway.mqtt_link.message import Counters, Message
from imu_gateway.mqtt_link.pipe import WINDOW, Pipe
from imu_gateway.supervise import PeerLog


class Handed:
    """paho's ``publish``, as far as the pipe sees it: each message queued, its info
    published when the test says paho wrote (QoS 0) or had it acknowledged."""

    def __init__(self) -> None:
        self.infos: list[tuple[Message, paho.MQTTMessageInfo]] = []

    def publish(self, topic: str, payload: bytes, qos: int, retain: bool,
                properties: object = None) -> paho.MQTTMessageInfo:
        info = paho.MQTTMessageInfo(len(self.infos) + 1)
        info.rc = MQTTErrorCode.MQTT_ERR_SUCCESS
        self.infos.append((Message(topic, payload, qos, retain), info))
        return info

    def done(self, qos: int) -> int:
        """paho wrote (or had acknowledged) every message of ``qos`` handed so far."""
        count = 0
        for message, info in self.infos:
            if message.qos == qos and not info.is_published():
                info._set_as_published()
                count += 1
        return count


@pytest.mark.anyio
async def test_a_result_never_acknowledged_holds_one_place_not_the_window() -> None:
    """A command result (QoS 1) whose acknowledgement never comes, then 3 windows of
    states (QoS 0), each written: every state goes through, and the result holds one
    place of the window (before, counted in order, it held them all)."""
    await asyncio.sleep(0)
    handed, counters = Handed(), Counters()
    pipe = Pipe(10 * WINDOW, counters, PeerLog(logging.getLogger("test")),
                lambda: handed, lambda: True)  # type: ignore[arg-type,return-value]
    pipe.send_control(Message("imu/gw/s/cmd/zero/result", b"{}", 1, False))
    for n in range(3 * WINDOW):
        pipe.send(Message("imu/gw/s/state", b"%d" % n, 0, False))
    while pipe.outbox:
        assert pipe.in_window() == WINDOW
        assert handed.done(0) > 0
        pipe.settle()
    handed.done(0)
    pipe.settle()
    assert [m.payload for m, _ in handed.infos if m.qos == 0] == \
        [b"%d" % n for n in range(3 * WINDOW)]  # (every one, in order)
    assert pipe.in_window() == 1 and counters.written == 3 * WINDOW
    handed.done(1)  # (its acknowledgement, at last)
    pipe.settle()
    assert pipe.in_window() == 0 and counters.written == 3 * WINDOW + 1
