"""States out over MQTT: each sensor's reading JSON on its state topic (held to
``min_interval_ms``, held back within the deadbands), its per-field topics, and its
availability.

State topics are last-value topics.  While the broker is away no state is queued: a
subscriber (Home Assistant) stamps a message with the time it arrives, so a replayed
burst of old states would write a false history, and the latest would come twice.
After a connect each sensor's latest state goes out once.  What was missed is dropped
and counted, or, with ``mqtt.backfill``, sent afterwards on the sensor's history topic
with its own ``ts``, at most ``backfill_per_s`` a second (``Backfill``).
"""

from __future__ import annotations

import asyncio
import json
import math
from collections import deque
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass

from ...cache import EventKind, Snapshot, Status
from ...config import MqttConfig
from ...derived import reading_json, values_of
from ...mqtt_link.message import Message, json_properties
from ..common import GatewayLike
from .side import SideTopics
from .topics import (
    CONTROL_QOS,
    OFFLINE,
    ONLINE,
    Topics,
    send_delay,
    within_deadband,
)


@dataclass(slots=True)
class _SensorOut:
    """What was last sent for one sensor, for the throttle and the deadband."""

    sent_at: float = -math.inf  # loop time of the last state message
    values: Mapping[str, float] | None = None  # the field values it carried
    status: Status | None = None
    availability: bytes | None = None
    trailing: asyncio.TimerHandle | None = None  # min_interval's deferred send


class Backfill:
    """The state messages a sensor missed while the broker was away, oldest first, at
    most ``size`` (the oldest dropped first): sent after a connect on the sensor's
    ``history`` topic, never retained, at most ``per_s`` a second."""

    def __init__(self, size: int, per_s: float, topics: Topics,
                 send: Callable[[Message], None], connected: Callable[[], bool]) -> None:
        self.kept: deque[Message] = deque(maxlen=size)
        self.per_s = per_s
        self.topics = topics
        self.send = send
        self.connected = connected
        self.dropped = 0
        self.sent = 0
        self._timer: asyncio.TimerHandle | None = None

    def keep(self, state: Message, sensor: str, older: bool = False) -> None:
        """Keeps a missed state; ``older``: older than every one kept (a state that
        waited in the queue when the connection went), so it goes first, or, when
        the backfill is full, is the one dropped."""
        message = Message(self.topics.sensor(sensor, "history"), state.payload, state.qos,
                          False, state.properties)
        if len(self.kept) == self.kept.maxlen:
            self.dropped += 1
            if older:
                return
        if older:
            self.kept.appendleft(message)
        else:
            self.kept.append(message)

    def sent_live(self, state: Message, sensor: str) -> None:
        """``state`` went out on the state topic after all (the latest, at a connect):
        it is not missed."""
        history = self.topics.sensor(sensor, "history")
        for kept in reversed(self.kept):
            if kept.topic == history:
                if kept.payload == state.payload:
                    self.kept.remove(kept)
                return

    def resume(self) -> None:
        """(After a connect) send what was kept, paced."""
        if self._timer is None and self.kept:
            self._timer = asyncio.get_running_loop().call_later(1 / self.per_s, self._next)

    def _next(self) -> None:
        self._timer = None
        if self.connected() and self.kept:
            self.send(self.kept.popleft())
            self.sent += 1
            self.resume()

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def forget(self, sensors: Collection[str]) -> None:
        """The states kept of sensors a reload removed: dropped (they publish no more)."""
        gone = {self.topics.sensor(name, "history") for name in sensors}
        kept = [m for m in self.kept if m.topic not in gone]
        self.kept.clear()
        self.kept.extend(kept)


class StateDesk:
    """Sends what the cache says of the sensors, as the MQTT client's config asks.

    ``send`` queues a state, ``send_control`` a message that must not be dropped
    (availability); ``connected`` says whether the client is connected now, and
    ``take_waiting`` takes the states queued and not yet handed over."""

    def __init__(self, gateway: GatewayLike, config: MqttConfig, topics: Topics,
                 send: Callable[[Message], None],
                 send_control: Callable[[Message], None],
                 connected: Callable[[], bool],
                 take_waiting: Callable[[], list[Message]]) -> None:
        self.gateway = gateway
        self.config = config
        self.topics = topics
        self.send = send
        self.send_control = send_control
        self.connected = connected
        self.take_waiting = take_waiting
        self._deadbands = config.field_deadbands()
        self._sensors = {name: _SensorOut() for name in gateway.sensors}
        self.missed = 0  # state and per-field messages not sent: the broker was away
        self._json = json_properties(config, config.state_expiry_s)
        self.backfill = Backfill(config.queue_size, config.backfill_per_s, topics, send,
                                 connected) if config.backfill else None
        self.side = SideTopics(gateway, config, topics, send, send_control, connected)

    def announce(self) -> None:
        """Every sensor's availability and latest state, anew (after a connect), as
        heard (``Cache.heard``).  The states still queued from before are old news: to
        the backfill, or dropped."""
        with self.gateway.cache.heard():
            self._announce()

    def _announce(self) -> None:
        for message in reversed(self.take_waiting()):  # the newest first, each in front
            self._miss(message, older=True)
        for snap in self.gateway.cache.snapshots():
            self._out(snap.name).availability = None
            self._publish_availability(snap)
        for snap in self.gateway.cache.snapshots():
            if snap.has_reading:
                state = self._publish_state(snap)
                if state is not None and self.backfill is not None:
                    self.backfill.sent_live(state, snap.name)
        if self.backfill is not None:
            self.backfill.resume()
        self.side.announce()

    def sensors_changed(self, announced: Collection[str]) -> None:
        """A reload changed the gateway's sensors: the removed ones are forgotten
        (their deferred sends dropped), and the ``announced`` ones (added or changed)
        have their availability and settings sent anew; their state goes with their
        next reading."""
        gone = [name for name in self._sensors if name not in self.gateway.sensors]
        for name in gone:
            trailing = self._sensors.pop(name).trailing
            if trailing is not None:
                trailing.cancel()
        self.side.forget(gone)
        if self.backfill is not None:
            self.backfill.forget(gone)
        with self.gateway.cache.heard():
            for name in announced:
                self._out(name).availability = None
                self._publish_availability(self.gateway.cache.snapshot(name))
            self.side.announce(announced)

    def _out(self, name: str) -> _SensorOut:
        """What was sent for a sensor (a sensor a reload just added: nothing yet; its
        events may come before the reload tells this desk of it)."""
        out = self._sensors.get(name)
        if out is None:
            out = self._sensors[name] = _SensorOut()
        return out

    def _miss(self, message: Message, older: bool = False) -> None:
        sensor, _, leaf = message.topic.removeprefix(self.topics.prefix + "/").rpartition("/")
        if self.backfill is not None and leaf == "state":
            self.backfill.keep(message, sensor, older)
        else:
            self.missed += 1

    def cancel(self) -> None:
        """Drop the deferred sends (the client is stopping)."""
        self.side.cancel()
        if self.backfill is not None:
            self.backfill.cancel()
        for out in self._sensors.values():
            if out.trailing is not None:
                out.trailing.cancel()
                out.trailing = None

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.STATUS:
            self._publish_availability(snap)
            out = self._out(snap.name)
            if snap.has_reading and out.status is not None and snap.status is not out.status:
                self._publish_state(snap)
        elif kind is EventKind.READING:
            self._consider(snap)
        self.side.on_cache_event(kind, snap)

    def _publish_availability(self, snap: Snapshot) -> None:
        if not self.connected():
            return  # not queued: the next connect publishes the availability of then
        out = self._out(snap.name)
        payload = OFFLINE if snap.status is Status.OFFLINE else ONLINE
        if payload != out.availability:
            out.availability = payload
            self.send_control(Message(self.topics.sensor(snap.name, "availability"),
                                      payload, CONTROL_QOS, True))

    def _consider(self, snap: Snapshot) -> None:
        """A new reading: send it now, later (min_interval) or not (deadband)."""
        out = self._out(snap.name)
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
        with self.gateway.cache.heard():
            snap = self.gateway.cache.snapshot(name)
        if snap.has_reading and not self._within_deadband(snap, self._sensors[name]):
            self._publish_state(snap)

    def _within_deadband(self, snap: Snapshot, out: _SensorOut) -> bool:
        return bool(self._deadbands) and snap.reading is not None and within_deadband(
            values_of(snap), out.values, self._deadbands)

    def _publish_state(self, snap: Snapshot) -> Message | None:
        """Sends the state (and the per-field values); returns the state message, or
        ``None`` when it was missed."""
        assert snap.reading is not None
        c = self.config
        state = Message(self.topics.sensor(snap.name, "state"), reading_json(snap),
                        c.qos, c.retain, self._json)
        values = values_of(snap)
        fields = [Message(self.topics.sensor(snap.name, name), json.dumps(value).encode(),
                          c.qos, c.retain, self._json)
                  for name, value in values.items() if math.isfinite(value)] \
            if c.per_field_topics else []  # (a plain number or nothing)
        if not self.connected():  # not queued: the next connect sends the latest
            for message in (state, *fields):
                self._miss(message)
            return None
        out = self._out(snap.name)
        out.sent_at = asyncio.get_running_loop().time()
        out.values = values
        out.status = snap.status
        for message in (state, *fields):
            self.send(message)
        return state
