"""The topics beside a sensor's state (docs/mqtt.md):

* ``{prefix}/{sensor}/settings``: the settings the gateway knows (``KnownSettings``),
  retained, sent when they change;
* ``{prefix}/diagnostics``: each bus's and sensor's counters, retained, every
  ``DIAGNOSTICS_S``;
* ``{prefix}/{sensor}/ha``: with Home Assistant discovery, the state again, for Home
  Assistant's entities, at most once per ``homeassistant_min_interval_ms`` (and at
  once when the status changes): Home Assistant records every state change, and a
  100 Hz stream would flood its database.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Collection
from typing import Any

from ...cache import EventKind, Snapshot, Status
from ...config import MqttConfig
from ...derived import reading_json
from ...mqtt_link.message import Message, json_properties
from ..common import GatewayLike, json_bytes
from .topics import (
    CONTROL_QOS,
    HA_LEAF,
    SETTINGS_LEAF,
    Topics,
    send_delay,
)

DIAGNOSTICS_S = 10.0


class SideTopics:
    """Sends the side topics of one MQTT client.  ``send`` queues a message that may
    be dropped, ``send_control`` one that must not be (one per topic)."""

    def __init__(self, gateway: GatewayLike, config: MqttConfig, topics: Topics,
                 send: Callable[[Message], None], send_control: Callable[[Message], None],
                 connected: Callable[[], bool]) -> None:
        self.gateway = gateway
        self.topics = topics
        self.send = send
        self.send_control = send_control
        self.connected = connected
        self._json = json_properties(config)
        self._ha_interval = config.homeassistant_min_interval_ms / 1000 \
            if config.homeassistant_discovery else None
        self._ha_sent: dict[str, tuple[float, Status]] = {}
        self._ha_trailing: dict[str, asyncio.TimerHandle] = {}
        self._diagnostics: asyncio.TimerHandle | None = None

    def announce(self, sensors: Collection[str] | None = None) -> None:
        """After a connect: every sensor's settings and Home Assistant state, and the
        diagnostics (then every ``DIAGNOSTICS_S``); after a reload, those of the
        ``sensors`` it added or changed."""
        for snap in self.gateway.cache.snapshots():
            if sensors is not None and snap.name not in sensors:
                continue
            self._send_settings(snap.name)
            if snap.has_reading:
                self._ha_state(snap)
        if sensors is None:
            self._send_diagnostics()

    def forget(self, sensors: Collection[str]) -> None:
        """Sensors a reload removed: their deferred Home Assistant states dropped."""
        for name in sensors:
            self._ha_sent.pop(name, None)
            timer = self._ha_trailing.pop(name, None)
            if timer is not None:
                timer.cancel()

    def cancel(self) -> None:
        for timer in (*self._ha_trailing.values(), self._diagnostics):
            if timer is not None:
                timer.cancel()
        self._ha_trailing.clear()
        self._diagnostics = None

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.SETTINGS:
            self._send_settings(snap.name)
        elif self._ha_interval is not None and snap.has_reading and self.connected():
            sent = self._ha_sent.get(snap.name)
            if kind is EventKind.STATUS and sent is not None and sent[1] is snap.status:
                return  # a change Home Assistant does not see (busy, streaming)
            if kind is EventKind.STATUS or sent is None:
                self._ha_state(snap)  # a status change goes at once
            elif snap.name not in self._ha_trailing:
                self._ha_later(snap.name, sent[0])

    def _send_settings(self, name: str) -> None:
        if self.connected():
            known = self.gateway.cache.settings(name)
            self.send_control(Message(self.topics.sensor(name, SETTINGS_LEAF),
                                      json_bytes(known.to_json()), CONTROL_QOS, True,
                                      self._json))

    def _ha_later(self, name: str, sent_at: float) -> None:
        assert self._ha_interval is not None
        loop = asyncio.get_running_loop()
        wait = send_delay(sent_at, self._ha_interval, loop.time())
        if wait <= 0:
            with self.gateway.cache.heard():
                snap = self.gateway.cache.snapshot(name)
            self._ha_state(snap)
        else:
            self._ha_trailing[name] = loop.call_later(wait, self._ha_trailing_send, name)

    def _ha_trailing_send(self, name: str) -> None:
        self._ha_trailing.pop(name, None)
        with self.gateway.cache.heard():
            snap = self.gateway.cache.snapshot(name)
        if snap.has_reading and self.connected():
            self._ha_state(snap)

    def _ha_state(self, snap: Snapshot) -> None:
        if self._ha_interval is None:
            return
        timer = self._ha_trailing.pop(snap.name, None)
        if timer is not None:
            timer.cancel()
        self._ha_sent[snap.name] = (asyncio.get_running_loop().time(), snap.status)
        self.send(Message(self.topics.sensor(snap.name, HA_LEAF), reading_json(snap),
                          CONTROL_QOS, True, self._json))

    def _send_diagnostics(self) -> None:
        loop = asyncio.get_running_loop()
        if self._diagnostics is not None:
            self._diagnostics.cancel()
        self._diagnostics = loop.call_later(DIAGNOSTICS_S, self._send_diagnostics)
        if self.connected():
            self.send_control(Message(self.topics.diagnostics,
                                      json_bytes(self.diagnostics()), CONTROL_QOS, True,
                                      self._json))

    def diagnostics(self) -> dict[str, Any]:
        """The diagnostics JSON: per bus and per sensor, the counters Home Assistant's
        diagnostic entities show."""
        buses = {b.name: {"utilisation": round(100 * b.utilisation, 2),
                          "transactions_per_s": b.transactions_per_s,
                          "errors": sum(b.errors.values())}
                 for b in self.gateway.stats()}
        sensors = {}
        for name in self.gateway.sensors:
            stats = self.gateway.sensor_stats(name)
            latency = stats.latency_ms
            sensors[name] = {"achieved_hz": stats.achieved_hz,
                             "latency_ms": latency if latency is not None
                             and math.isfinite(latency) else None,
                             "errors": sum(stats.errors.values())}
        return {"buses": buses, "sensors": sensors}
