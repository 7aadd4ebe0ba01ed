"""The alarms over MQTT (docs/mqtt.md, "Alarms"; docs/alarms.md).

Each alarm's state is retained on ``{prefix}/{sensor}/alarm/{alarm}``, as REST's
``GET /api/v1/alarms`` gives it: every alarm at each connect, and each one again at
its transitions (the cache's ``ALARM`` events).  Nothing is done per sample: the
alarms are evaluated once, by the gateway, and this only hears what they decided.

An acknowledgement comes in on that topic with ``/ack`` appended, taken by the
command desk (``commands.CommandDesk.take_ack``) as commands are, with its rules:
only with ``allow_commands``, never from a retained or empty message, the result on
the MQTT 5 response topic or the topic with ``/result`` appended.  Its payload is a
JSON object, ``{}`` or ``{"by": "alice"}`` (who acknowledges, for the journal).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Collection, Mapping
from typing import Any

from ...alarms import AlarmState
from ...cache import EventKind, Snapshot
from ...config import MqttConfig
from ...errors import ErrorKind, RequestFailed
from ...mqtt_link.message import Message, json_properties
from ..common import GatewayLike, json_bytes
from .topics import CONTROL_QOS, Topics

#: Who acknowledged, in the journal: ``mqtt``, or ``alice (mqtt)`` with ``{"by": "alice"}``
#: (MQTT does not say which client published a message).
ACKNOWLEDGER = "mqtt"
BY = "by"
MAX_BY = 64  # as REST's ``?by=``
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


class AlarmDesk:
    """Publishes every alarm's state, retained.  ``send_control`` queues a message that
    must not be dropped (one per topic: a newer state replaces one still waiting)."""

    def __init__(self, gateway: GatewayLike, config: MqttConfig, topics: Topics,
                 send_control: Callable[[Message], None],
                 connected: Callable[[], bool]) -> None:
        self.gateway = gateway
        self.topics = topics
        self.send_control = send_control
        self.connected = connected
        self._json = json_properties(config)

    def announce(self, sensors: Collection[str] | None = None) -> None:
        """After a connect: every alarm's state (after a reload: the alarms of the
        ``sensors`` it added or changed)."""
        for state in self.gateway.alarm_states():
            if sensors is None or state.sensor in sensors:
                self._send(state)

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        """The cache's ``ALARM`` events (the only kind this listens to)."""
        if kind is EventKind.ALARM and snap.alarm is not None:
            self._send(snap.alarm.state)

    def _send(self, state: AlarmState) -> None:
        if self.connected():  # (not queued: the next connect sends the state of then)
            self.send_control(Message(self.topics.alarm(state.sensor, state.name),
                                      json_bytes(state.to_json()), CONTROL_QOS, True,
                                      self._json))


def acknowledger(args: Mapping[str, Any]) -> str:
    """Who acknowledges, from an acknowledgement's arguments; raises ``RequestFailed``
    (``bad_arguments``) for a key other than ``by`` or a ``by`` that is not a short
    line of text."""
    unknown = sorted(set(args) - {BY})
    if unknown:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"unknown argument {unknown[0]!r}: an "
                            f"acknowledgement takes only {BY!r} (who acknowledges)")
    if BY not in args:
        return ACKNOWLEDGER
    by = args[BY]
    if not isinstance(by, str) or not 1 <= len(by) <= MAX_BY or _CONTROL.search(by):
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"{BY} must be a string of 1 to "
                            f"{MAX_BY} characters without control characters")
    return f"{by} ({ACKNOWLEDGER})"


def ack_result(sensor: str, alarm: str, state: AlarmState | None,
               error: RequestFailed | None = None) -> dict[str, Any]:
    """An acknowledgement's result: the alarm's state after it, or why it failed."""
    return {"ok": error is None, "sensor": sensor, "alarm": alarm,
            "state": None if state is None else state.to_json(),
            "error": None if error is None else str(error),
            "kind": None if error is None else error.kind.value}
