"""States out over MQTT: each sensor's reading JSON on its state topic (held to
``min_interval_ms``, held back within the deadbands), its per-field topics, and its
availability."""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import Callable
from dataclasses import dataclass

from ..cache import EventKind, Snapshot, Status
from ..config import MqttConfig
from ..normalise import field_values
from .common import GatewayLike, json_bytes
from .mqtt_topics import (
    CONTROL_QOS,
    OFFLINE,
    ONLINE,
    Message,
    Topics,
    send_delay,
    within_deadband,
)


@dataclass(slots=True)
class _SensorOut:
    """What was last sent for one sensor, for the throttle and the deadband."""

    sent_at: float = -math.inf  # loop time of the last state message
    values: dict[str, float] | None = None  # the field values it carried
    status: Status | None = None
    availability: bytes | None = None
    trailing: asyncio.TimerHandle | None = None  # min_interval's deferred send


class StateDesk:
    """Sends what the cache says of the sensors, as the MQTT client's config asks.

    ``send`` queues a state (dropped first when the broker is away), ``send_control``
    a message that must not be dropped (availability); ``connected`` says whether the
    client is connected now."""

    def __init__(self, gateway: GatewayLike, config: MqttConfig, topics: Topics,
                 send: Callable[[Message], None],
                 send_control: Callable[[Message], None],
                 connected: Callable[[], bool]) -> None:
        self.gateway = gateway
        self.config = config
        self.topics = topics
        self.send = send
        self.send_control = send_control
        self.connected = connected
        self._deadbands = config.field_deadbands()
        self._sensors = {name: _SensorOut() for name in gateway.sensors}

    def announce(self) -> None:
        """Every sensor's availability and latest state, anew (after a connect)."""
        for snap in self.gateway.cache.snapshots():
            self._sensors[snap.name].availability = None
            self._publish_availability(snap)
        for snap in self.gateway.cache.snapshots():
            if snap.has_reading:
                self._publish_state(snap)

    def cancel(self) -> None:
        """Drop the deferred sends (the client is stopping)."""
        for out in self._sensors.values():
            if out.trailing is not None:
                out.trailing.cancel()
                out.trailing = None

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.STATUS:
            self._publish_availability(snap)
            out = self._sensors[snap.name]
            if snap.has_reading and out.status is not None and snap.status is not out.status:
                self._publish_state(snap)
        elif kind is EventKind.READING:
            self._consider(snap)

    def _publish_availability(self, snap: Snapshot) -> None:
        if not self.connected():
            return  # not queued: the next connect publishes the availability of then
        out = self._sensors[snap.name]
        payload = OFFLINE if snap.status is Status.OFFLINE else ONLINE
        if payload != out.availability:
            out.availability = payload
            self.send_control(Message(self.topics.sensor(snap.name, "availability"),
                                      payload, CONTROL_QOS, True))

    def _consider(self, snap: Snapshot) -> None:
        """A new reading: send it now, later (min_interval) or not (deadband)."""
        out = self._sensors[snap.name]
        if out.trailing is not None:
            return  # the deferred send will take the latest reading
        if self._within_deadband(snap, out):
            return
        loop = asyncio.get_running_loop()
        wait = send_delay(out.sent_at, self.config.min_interval_ms / 1000, loop.time())
        if wait > 0:
            out.trailing = loop.call_later(wait, self._send_trailing, snap.name)
            return
        self._publish_state(snap)

    def _send_trailing(self, name: str) -> None:
        self._sensors[name].trailing = None
        snap = self.gateway.cache.snapshot(name)
        if snap.has_reading and not self._within_deadband(snap, self._sensors[name]):
            self._publish_state(snap)

    def _within_deadband(self, snap: Snapshot, out: _SensorOut) -> bool:
        return snap.reading is not None and within_deadband(
            field_values(snap.reading), out.values, self._deadbands)

    def _publish_state(self, snap: Snapshot) -> None:
        assert snap.reading is not None
        out = self._sensors[snap.name]
        out.sent_at = asyncio.get_running_loop().time()
        out.values = field_values(snap.reading)
        out.status = snap.status
        c = self.config
        self.send(Message(self.topics.sensor(snap.name, "state"), json_bytes(snap.to_json()),
                          c.qos, c.retain))
        if c.per_field_topics:
            for name, value in out.values.items():
                if math.isfinite(value):  # a plain number or nothing
                    self.send(Message(self.topics.sensor(snap.name, name),
                                      json.dumps(value).encode(), c.qos, c.retain))
