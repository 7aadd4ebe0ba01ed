"""What the MQTT transport carries: one message to publish, and the client's running
totals.  Both MQTT front ends (plain topics and Sparkplug B) hand their messages to
the session in this shape.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from ..config import MqttConfig


class Message(NamedTuple):
    """One message to publish."""

    topic: str
    payload: bytes
    qos: int
    retain: bool
    properties: Properties | None = None


def json_properties(config: MqttConfig, expiry_s: int | None = None) -> Properties | None:
    """MQTT 5's description of a JSON message: its content type, UTF-8 (payload format
    indicator 1), and how long the broker may keep it for a subscriber (``None``
    under 3.1.1, which has no properties)."""
    if config.protocol != "5":
        return None
    properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
    properties.ContentType = "application/json"
    properties.PayloadFormatIndicator = 1
    if expiry_s is not None:
        properties.MessageExpiryInterval = expiry_s
    return properties


@dataclass(slots=True)
class Counters:
    """The MQTT client's running totals (its ``stats()``)."""

    published: int = 0  # handed to paho
    written: int = 0  # written (QoS 0) or acknowledged: paho says it is published
    undeliverable: int = 0  # paho can never send it (a bad topic): dropped
    ignored: int = 0  # commands not run: retained, empty, too large, bad properties
    lost_in_flight: int = 0  # handed to paho, unwritten or unacknowledged when it went
    commands: int = 0
    command_errors: int = 0
    connects: int = 0
