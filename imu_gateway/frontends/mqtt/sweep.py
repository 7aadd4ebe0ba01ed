"""After each connect, the retained messages this gateway left on the broker and no
longer publishes are removed: the Home Assistant discovery configs of entities that
are gone, and the state, availability and per-field topics of sensors that left the
config (or per-field values turned off), and the states of alarms that left it.
Otherwise they would stay on the broker for ever, a removed sensor saying
``"status": "ok"``.

For ``SWEEP_S`` after a connect the client subscribes to its own topics and to the
discovery configs; the broker sends the retained ones at once.  Each that this
gateway does not publish any more is cleared with an empty retained message, the
MQTT way to delete one.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Collection, Mapping
from typing import Any

import paho.mqtt.client as paho

from ...mqtt_link.message import Message
from .topics import ALARM_LEAF, CONTROL_QOS, Topics

log = logging.getLogger("imu_gateway.mqtt")

SWEEP_S = 5.0  # how long after connecting old retained messages are looked for


class RetainedSweep:
    """Clears what this gateway retained once and publishes no more.

    ``discovery``: the discovery topics it publishes now; ``leaves``: per sensor, the
    retained leaves of ``{prefix}/{sensor}/…`` it publishes now."""

    def __init__(self, topics: Topics, discovery_prefix: str | None,
                 discovery: Collection[str], leaves: Mapping[str, Collection[str]],
                 send_control: Callable[[Message], None]) -> None:
        self.topics = topics
        self.discovery_prefix = discovery_prefix
        self.discovery = discovery
        self.leaves = leaves
        self.send_control = send_control
        self.until = 0.0
        self.cleared = 0

    def subscriptions(self) -> list[str]:
        """What to subscribe to for the sweep (and unsubscribe from after it)."""
        own = [f"{self.topics.prefix}/+/+", f"{self.topics.prefix}/+/{ALARM_LEAF}/+"]
        return own if self.discovery_prefix is None else \
            [*own, f"{self.discovery_prefix}/+/+/config"]

    def start(self, client: paho.Client, now: float) -> None:
        self.until = now + SWEEP_S
        for topic in self.subscriptions():
            # QoS 0: a read of retained messages needs no more, and NATS makes a
            # JetStream consumer for each QoS 1 subscription, holding the connection's
            # later packets meanwhile (docs/mqtt.md)
            client.subscribe(topic, qos=0)

    def end(self, client: paho.Client) -> None:
        for topic in self.subscriptions():
            client.unsubscribe(topic)

    def take(self, message: paho.MQTTMessage, now: float) -> None:
        """A message of the sweep's subscriptions: a retained one, while the sweep
        lasts, is cleared when this gateway no longer publishes it (a live one, or one
        after the sweep, is none of its business)."""
        if not message.retain or not message.payload or now > self.until:
            return
        topic = message.topic
        if self.discovery_prefix is not None and \
                topic.startswith(f"{self.discovery_prefix}/"):
            if topic not in self.discovery and _ours(bytes(message.payload), self.topics.prefix):
                self._clear(topic, "the discovery config")
            return
        sensor, _, leaf = topic.removeprefix(f"{self.topics.prefix}/").partition("/")
        if leaf not in self.leaves.get(sensor, ()):
            self._clear(topic, "the retained")

    def _clear(self, topic: str, what: str) -> None:
        log.info("mqtt: removing %s %s: this gateway no longer publishes it", what, topic)
        self.cleared += 1
        self.send_control(Message(topic, b"", CONTROL_QOS, True))


def _ours(payload: bytes, prefix: str) -> bool:
    """Whether a discovery config belongs to this gateway: it reads one of its topics
    (another gateway's configs share the discovery prefix)."""
    try:
        config: Any = json.loads(payload)
    except (ValueError, RecursionError):
        return False
    if not isinstance(config, dict):
        return False
    read = [config.get(key) for key in ("state_topic", "command_topic", "json_attributes_topic")]
    return any(isinstance(t, str) and t.startswith(prefix + "/") for t in read)
