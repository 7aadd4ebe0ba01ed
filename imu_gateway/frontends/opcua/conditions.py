"""The alarms as OPC UA Part 9 conditions (docs/opcua.md, "Alarms and conditions").

Each alarm is a condition object under its sensor (``…Sensors.{sensor}.Alarms.{alarm}``):
an ``ExclusiveLimitAlarmType`` for a configured alarm, an ``OffNormalAlarmType`` for the
communication alarm.  The gateway object and each sensor object are event notifiers
(``Server`` ─HasNotifier→ gateway ─HasNotifier→ sensor ─HasCondition→ condition).

asyncua (2.1) carries little of Part 9, so this module holds the rest, in the least
code:

* **Events.** asyncua gives an event only to the monitored items of the one node it
  names as its emitter, not to those of the notifiers above it: each transition is
  given to the sensor's, the gateway object's and the Server's monitored items here.
  A transition's event is a new event object made when the transition comes (the
  cache's ``ALARM`` event), so two transitions in flight never share fields; events
  are sent in order by one task.  Nothing is done per sample.
* **Acknowledge.** asyncua has no condition methods: ``AcknowledgeableConditionType``'s
  ``Acknowledge`` is bound here, checked (rights, arguments, EventId), then run
  through the gateway's ``acknowledge``.
* **ConditionRefresh.** asyncua's own (``bind_condition_methods``) resends a retained
  condition only to items on its emitter's node, and keeps whatever event came last:
  it is replaced here by one that resends each retained condition to every notifier
  the subscription watches, between RefreshStart and RefreshEnd events.

The condition objects carry their type, their limits and a HasCondition from their
sensor; their state is in the events (and a ConditionRefresh), not in variables.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import uuid
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common import event_objects

from ...alarms import AlarmEvent, AlarmRow, AlarmState, Severity, State, communication_row
from ...errors import ErrorKind, RequestFailed
from ..common import GatewayLike
from .nodes import ALARMS, Ids, add_node

log = logging.getLogger("imu_gateway.opcua")

#: Part 9's Severity of each of the gateway's severities (1 … 1000).
SEVERITY = {Severity.INFO: 200, Severity.WARNING: 500, Severity.CRITICAL: 800}
#: How many of a condition's latest EventIds an Acknowledge may name.
EVENT_IDS_KEPT = 16



@dataclass(frozen=True, slots=True)
class Caller:
    """Who calls a method: the session's user name (None: anonymous), the peer's
    address and the session's id."""

    user: str | None
    peer: str
    session: ua.NodeId


#: Who is calling a method now (set by guard.GuardedProcessor for each Call request).
CALLER: contextvars.ContextVar[Caller | None] = contextvars.ContextVar("opcua_caller",
                                                                      default=None)

_S = ua.StatusCodes


@dataclass(slots=True)
class Condition:
    """One alarm's condition: where it is, and what it last said."""

    row: AlarmRow
    node: ua.NodeId  # the ConditionId
    source: ua.NodeId  # the sensor object
    input_node: ua.NodeId | None  # the variable the alarm watches (Status: communication)
    last: Any = None  # the latest event object (its fields are the condition's state)
    event_ids: deque[bytes] = field(default_factory=lambda: deque(maxlen=EVENT_IDS_KEPT))
    comment: str = ""  # the latest acknowledgement's comment (Part 9's Comment)


def _text(text: str) -> ua.LocalizedText:
    return ua.LocalizedText(text, "en")


def message(state: AlarmState, by: str | None) -> str:
    """The event's Message: the alarm, its state, and the value against the limit."""
    what = f"{state.sensor}/{state.name} {state.state.value}"
    if state.field is None:
        return f"{what} (the sensor is stale or offline)" if state.active else what
    if by is not None:
        return f"{what}, acknowledged by {by}"
    if state.value is None:
        return what
    return f"{what}: {state.field} {state.value:g} (limit {state.limit:g})" \
        if state.limit is not None else f"{what}: {state.field} {state.value:g}"


def event_of(cond: Condition, state: AlarmState, at: float, by: str | None,
             active_since: datetime | None) -> Any:
    """A new event object with the condition's fields after a transition (or at start)."""
    row = cond.row
    limit = row.field is not None
    event = event_objects.ExclusiveLimitAlarm() if limit else event_objects.OffNormalAlarm()
    event.add_property("NodeId", cond.node, ua.VariantType.NodeId)  # the ConditionId
    event.add_property("Value", state.value, ua.VariantType.Double)  # (the gateway's own)
    event.emitting_node = cond.source
    event.EventId = uuid.uuid4().bytes
    event.SourceNode, event.SourceName = cond.source, row.sensor
    event.Time = datetime.fromtimestamp(at, UTC)
    event.ReceiveTime = datetime.now(UTC)
    event.Message = _text(message(state, by))
    event.Severity = event.LastSeverity = SEVERITY[state.severity]
    event.ConditionName = row.name
    event.ConditionClassId = ua.NodeId(ua.ObjectIds.ProcessConditionClassType if limit
                                       else ua.ObjectIds.SystemConditionClassType)
    event.ConditionClassName = _text("Process" if limit else "System")
    event.BranchId = ua.NodeId()
    event.Retain = state.state is not State.NORMAL
    event.EnabledState, event.__dict__["EnabledState/Id"] = _text("Enabled"), True
    event.Quality = ua.StatusCode(_S.Good)
    event.Comment, event.ClientUserId = _text(cond.comment), by or ""
    acked, active = state.acked, state.active
    event.AckedState = _text("Acknowledged" if acked else "Unacknowledged")
    event.__dict__["AckedState/Id"] = acked
    event.ActiveState = _text("Active" if active else "Inactive")
    event.__dict__["ActiveState/Id"] = active
    event.__dict__["ActiveState/TransitionTime"] = active_since
    event.data_types["ActiveState/TransitionTime"] = ua.VariantType.DateTime  # (not UtcTime's id)
    event.InputNode = cond.input_node
    event.SuppressedOrShelved = False
    if limit:
        event.HighLimit, event.LowLimit = row.above, row.below
        high = state.limit is not None and state.limit == row.above
        event.add_variable("LimitState/CurrentState",
                           _text(("High" if high else "Low") if active else ""),
                           ua.VariantType.LocalizedText)
        event.add_property("LimitState/CurrentState/Id", ua.NodeId(
            (ua.ObjectIds.ExclusiveLimitStateMachineType_High if high else
             ua.ObjectIds.ExclusiveLimitStateMachineType_Low) if active else 0),
            ua.VariantType.NodeId)
    return event


class Conditions:
    """The conditions of every alarm, their events, Acknowledge and ConditionRefresh."""

    def __init__(self, gateway: GatewayLike, allow_ack: bool) -> None:
        self.gateway, self.allow_ack = gateway, allow_ack
        self.by_node: dict[ua.NodeId, Condition] = {}
        self.by_alarm: dict[tuple[str, str], Condition] = {}
        self.notifiers: list[ua.NodeId] = []  # Server, the gateway object, each sensor
        self._queue: asyncio.Queue[Any] = asyncio.Queue()
        self._server: Server | None = None

    # ------------------------------------------------------------ the address space

    async def build(self, server: Server, gateway_node: Node) -> None:
        """The notifiers above the sensors, and the condition methods (the sensors'
        conditions are added by ``add_sensor``)."""
        self._server = server
        top = ua.NodeId(ua.ObjectIds.Server)
        await _notifier(server, top, gateway_node.nodeid)
        self.notifiers = [top, gateway_node.nodeid]
        session = server.iserver.isession
        session.add_method_callback(ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
                                    self.acknowledge)
        for method in (ua.ObjectIds.ConditionType_ConditionRefresh,
                       ua.ObjectIds.ConditionType_ConditionRefresh2):
            session.add_method_callback(ua.NodeId(method), self.refresh)

    async def add_sensor(self, name: str, sensor: Node, inputs: dict[str, ua.NodeId],
                         ns: int, gid: str) -> None:
        """A sensor a notifier under the gateway object, with a condition object per
        alarm, each in the state the alarms have now (at start: as the journal left
        them)."""
        assert self._server is not None, "build() first"
        await _notifier(self._server, self.notifiers[1], sensor.nodeid)
        self.notifiers.append(sensor.nodeid)
        ids = Ids(f"{gid}.Sensors.{name}.{ALARMS}", ns)
        folder = await sensor.add_folder(ids(), ids.name(ALARMS))
        for row in _rows(self.gateway).get(name, []):
            node = await _condition_node(folder, ids, row)
            await sensor.add_reference(node.nodeid, ua.ObjectIds.HasCondition, True, False)
            watched = inputs.get(row.field or "Status")
            cond = Condition(row, node.nodeid, sensor.nodeid, watched)
            self.by_node[node.nodeid] = self.by_alarm[(name, row.name)] = cond
        now = datetime.now(UTC).timestamp()
        for state in self.gateway.alarm_states():
            found = self.by_alarm.get((state.sensor, state.name))
            if state.sensor == name and found is not None:
                since = None if state.since is None else datetime.fromtimestamp(state.since, UTC)
                self._keep(found, event_of(found, state, state.since or now, None,
                                           since if state.active else None))

    def remove_sensor(self, name: str, sensor: ua.NodeId) -> None:
        """Forget a sensor's conditions (a reload removed it; its nodes are deleted by
        the caller): no event, Acknowledge or ConditionRefresh names them again."""
        for key in [k for k in self.by_alarm if k[0] == name]:
            del self.by_node[self.by_alarm.pop(key).node]
        if sensor in self.notifiers[2:]:
            self.notifiers.remove(sensor)

    def _keep(self, cond: Condition, event: Any) -> None:
        cond.last = event
        cond.event_ids.append(event.EventId)

    # ------------------------------------------------------------ transitions

    def on_alarm(self, change: AlarmEvent) -> None:
        """A transition (the cache's ``ALARM`` event): its event, made now, sent in
        order by ``run``."""
        t, state = change.transition, change.state
        cond = self.by_alarm.get((t.sensor, t.alarm))
        if cond is None:
            return
        before = cond.last
        since = before.__dict__.get("ActiveState/TransitionTime") if before is not None else None
        if t.from_state.active != t.to_state.active:
            since = datetime.fromtimestamp(t.at, UTC) if t.to_state.active else None
        event = event_of(cond, state, t.at, t.by, since)
        self._keep(cond, event)
        self._queue.put_nowait(event)

    async def run(self) -> None:
        """Send the events, one after the other (the front end's task)."""
        while True:
            event = await self._queue.get()
            try:
                await self.send(event, (event.SourceNode, *self.notifiers[:2]))
            except Exception:  # (a bug here must not end the server for the others)
                log.exception("opcua: an alarm event could not be sent")

    async def send(self, event: Any, notifiers: Iterable[ua.NodeId],
                   subscription: int | None = None) -> None:
        """Give ``event`` to the monitored items on each of ``notifiers`` (of one
        subscription, or of all)."""
        if self._server is None:
            return
        subs = self._server.iserver.subscription_service.subscriptions
        chosen = [subs[subscription]] if subscription is not None else list(subs.values())
        for notifier in notifiers:
            event.emitting_node = notifier
            for sub in chosen:
                await sub.monitored_item_srv.trigger_event(event)

    # ------------------------------------------------------------ methods

    async def acknowledge(self, parent: ua.NodeId, *args: Any) -> ua.StatusCode | list[Any]:
        """Part 9's Acknowledge(EventId, Comment), called on a condition (its
        ConditionId as the ObjectId)."""
        caller = CALLER.get()
        if not self.allow_ack or caller is None:
            return ua.StatusCode(_S.BadUserAccessDenied)
        cond = self.by_node.get(parent)
        if cond is None:
            return ua.StatusCode(_S.BadNodeIdUnknown)
        if len(args) != 2:
            return ua.StatusCode(_S.BadArgumentsMissing if len(args) < 2
                                 else _S.BadTooManyArguments)
        event_id, comment = (a.Value if isinstance(a, ua.Variant) else a for a in args)
        if not isinstance(event_id, bytes) or not isinstance(comment, ua.LocalizedText | None):
            return ua.StatusCode(_S.BadInvalidArgument)
        if event_id not in cond.event_ids:
            return ua.StatusCode(_S.BadEventIdUnknown)
        who = f"{caller.user} (opcua {caller.peer})" if caller.user else f"opcua {caller.peer}"
        before = cond.comment
        cond.comment = (comment.Text or "") if comment is not None else ""
        try:
            self.gateway.acknowledge(cond.row.sensor, cond.row.name, who)
        except RequestFailed as failed:
            cond.comment = before
            if failed.kind is ErrorKind.NOTHING_TO_ACKNOWLEDGE:
                return ua.StatusCode(_S.BadConditionBranchAlreadyAcked)
            raise
        return []

    async def refresh(self, parent: ua.NodeId, *args: Any) -> ua.StatusCode | list[Any]:
        """ConditionRefresh(SubscriptionId) and ConditionRefresh2(SubscriptionId,
        MonitoredItemId): every retained condition again, between RefreshStart and
        RefreshEnd, to the notifiers the subscription watches."""
        server, caller = self._server, CALLER.get()
        values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
        if server is None or caller is None or not values or not isinstance(values[0], int):
            return ua.StatusCode(_S.BadInvalidArgument)
        subscription = values[0]
        found = server.iserver.subscription_service.subscriptions.get(subscription)
        if found is None or found.session_id != caller.session:  # (only the session's own)
            return ua.StatusCode(_S.BadSubscriptionIdInvalid)
        await self.send(_refresh_event(event_objects.RefreshStartEvent()), self.notifiers,
                         subscription)
        for cond in self.by_node.values():
            if cond.last is not None and cond.last.Retain:
                await self.send(cond.last, (cond.source, *self.notifiers[:2]), subscription)
        await self.send(_refresh_event(event_objects.RefreshEndEvent()), self.notifiers,
                         subscription)
        return []


def _refresh_event(event: Any) -> Any:
    event.EventId = uuid.uuid4().bytes
    event.Time = event.ReceiveTime = datetime.now(UTC)
    event.SourceNode, event.SourceName = ua.NodeId(ua.ObjectIds.Server), "Server"
    event.Severity = 1
    return event


def _rows(gateway: GatewayLike) -> dict[str, list[AlarmRow]]:
    """Each sensor's alarms in config order, its communication alarm last."""
    return {s.name: [*(a.row(s.name) for a in s.alarms), communication_row(s.name)]
            for _, s in gateway.config.iter_sensors()}


async def _notifier(server: Server, parent: ua.NodeId, child: ua.NodeId) -> None:
    """``child`` an event notifier (SubscribeToEvents) under ``parent`` (HasNotifier)."""
    node = server.get_node(child)
    await node.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
    if parent == ua.NodeId(ua.ObjectIds.Server):
        await server.get_node(parent).set_event_notifier([ua.EventNotifier.SubscribeToEvents])
    await server.get_node(parent).add_reference(child, ua.ObjectIds.HasNotifier, True, False)


async def _condition_node(folder: Node, ids: Ids, row: AlarmRow) -> Node:
    """The condition object: its type, and its limits (HighLimit, LowLimit)."""
    attrs = ua.ObjectAttributes()
    attrs.Description = _text(f"alarm {row.name} of sensor {row.sensor}")
    attrs.EventNotifier = 0
    typedef = ua.ObjectIds.ExclusiveLimitAlarmType if row.field is not None \
        else ua.ObjectIds.OffNormalAlarmType
    node = await add_node(folder, ids(row.name), ids.name(row.name), ua.NodeClass.Object,
                          typedef, attrs)
    for prop, value in (("HighLimit", row.above), ("LowLimit", row.below)):
        if value is not None:
            await node.add_property(ids(f"{row.name}.{prop}"), ua.QualifiedName(prop, 0),
                                    ua.Variant(value, ua.VariantType.Double))
    return node
