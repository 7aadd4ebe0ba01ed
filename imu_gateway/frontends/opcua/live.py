"""A reload's sensors in the running address space (docs/opcua.md, "A reload"): a
sensor's subtree deleted with its monitored items told, and the ModelChangeEvent that
tells the clients which cache the address space to browse again.

asyncua (2.1) deletes nodes but gets the rest wrong, so this module does it:

* **Monitored items.**  OPC UA Part 4 (5.12) keeps a monitored
  item valid when its node is deleted, and has the server say ``Bad_NodeIdUnknown`` in
  the item's next notification.  asyncua's ``delete_nodes`` calls each item's
  (coroutine) callback without awaiting it, so nothing is ever sent; and it would have
  sent a subscription-wide StatusChangeNotification, not the item's.  Here a DataValue
  with StatusCode ``BadNodeIdUnknown`` (no value) is given to each item on a node about
  to go, as a data change, and the item's callback is dropped: the item stays (the
  client deletes it) and hears nothing more.
* **References.**  With ``DeleteTargetReferences`` asyncua scans every node in memory
  once per deleted node; only the sensor object is referenced from outside its subtree
  (its folder's Organizes, the gateway object's HasNotifier), so only its deletion
  asks for that scan.
* **The event.**  One ``GeneralModelChangeEventType`` per reload (OPC UA Part 3,
  9.32), from the Server object: each sensor object added (``NodeAdded``)
  or deleted (``NodeDeleted``), and the Sensors folder's references (``ReferenceAdded``,
  ``ReferenceDeleted``).  The gateway's nodes have no ``NodeVersion``.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import IntFlag
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common import event_objects

from ...alarms import AlarmRow


class Verb(IntFlag):
    """ModelChangeStructureDataType's Verb bits (OPC UA Part 5)."""

    NODE_ADDED = 1
    NODE_DELETED = 2
    REFERENCE_ADDED = 4
    REFERENCE_DELETED = 8


@dataclass(frozen=True, slots=True)
class Shape:
    """What a sensor's subtree is made of: a reload that changes any of it rebuilds
    the subtree; one that changes only the address writes the Address variable."""

    series: str
    protocol: str
    commands: tuple[str, ...]
    alarms: tuple[AlarmRow, ...]


@dataclass(frozen=True, slots=True)
class ModelChange:
    """One entry of a GeneralModelChangeEvent's Changes."""

    affected: ua.NodeId
    affected_type: ua.NodeId | None
    verb: Verb

    def structure(self) -> ua.ModelChangeStructureDataType:
        return ua.ModelChangeStructureDataType(
            Affected=self.affected, AffectedType=self.affected_type or ua.NodeId(),
            Verb=int(self.verb))


async def subtree(node: Node) -> list[Node]:
    """``node`` and every node below it by hierarchical references, children first."""
    found: list[Node] = []
    for child in await node.get_children():
        found += await subtree(child)
    found.append(node)
    return found


async def retire(server: Server, root: Node) -> int:
    """Delete ``root``'s subtree, its monitored items told ``BadNodeIdUnknown`` first;
    returns how many nodes went."""
    nodes = await subtree(root)
    aspace = server.iserver.aspace
    gone = ua.DataValue(StatusCode=ua.StatusCode(ua.StatusCodes.BadNodeIdUnknown),
                        SourceTimestamp=datetime.now(UTC), ServerTimestamp=datetime.now(UTC))
    for node in nodes:
        data = aspace.get(node.nodeid)
        value = None if data is None else data.attributes.get(ua.AttributeIds.Value)
        if value is None:
            continue
        # dropped before they are told, so that no sample written meanwhile comes after
        told = dict(value.datachange_callbacks)
        for handle in told:
            aspace.delete_datachange_callback(handle)
        for handle, callback in told.items():
            await callback(handle, gone)
    items = [ua.DeleteNodesItem(NodeId=n.nodeid, DeleteTargetReferences=n is root)
             for n in nodes]
    results = await server.iserver.isession.delete_nodes(
        ua.DeleteNodesParameters(NodesToDelete=items))
    for result in results:
        result.check()
    return len(nodes)


def model_change_event(changes: list[ModelChange]) -> Any:
    """The GeneralModelChangeEvent of a reload's changes, from the Server object."""
    event = event_objects.GeneralModelChangeEvent()
    event.EventId = uuid.uuid4().bytes
    event.Time = event.ReceiveTime = datetime.now(UTC)
    event.SourceNode, event.SourceName = ua.NodeId(ua.ObjectIds.Server), "Server"
    event.Severity = 1
    event.Message = ua.LocalizedText("the gateway's sensors changed: browse again", "en")
    event.Changes = [c.structure() for c in changes]
    # (asyncua declares the field with a DataType NodeId where it wants a VariantType)
    event.data_types["Changes"] = ua.VariantType.ExtensionObject
    return event


RELOAD_DOC = """## A reload: sensors added, removed or changed

A reload (`SIGHUP`, `systemctl reload imu-gateway`, `PUT /api/v1/config`; see
docs/configuration.md) that adds, removes or changes sensors, the `opcua:` section
unchanged, changes the address space in place: the server keeps listening, and every
session, subscription and monitored item stays.  The nodes of a sensor the reload
leaves alone do not change, and their subscriptions go on with no gap.

- **A sensor added** gets its whole subtree at once, as at a start: the same NodeIds,
  values, status and identity, methods, conditions and history.  Its values are
  `BadNoCommunication` until its first reading.
- **A sensor removed** loses its subtree: the sensor object and every node below it
  (folders, variables, properties, methods, conditions).  Read, Browse and
  HistoryRead of them are `BadNodeIdUnknown`, a Call `BadNodeIdInvalid` (asyncua's).
  Each monitored item on the Value of one of its nodes gets one last data change,
  StatusCode `BadNodeIdUnknown` and no value (OPC UA Part 4, 5.12: the item stays
  valid until the client deletes it); nothing more comes on it, nor on an item on the
  sensor object's events.
  Its conditions are in no event and no ConditionRefresh again; its values are
  written no more.
- **A sensor changed:** when its series, its bus's protocol or its alarms changed,
  its subtree is deleted as above and built
  again, with the same NodeIds: a client monitors the new nodes again (the old items
  were told `BadNodeIdUnknown`).  When only its address changed, its `Address`
  variable is written (its items hear the new value).  Any other setting (`poll_hz`,
  `unit_id`, `stale_after_ms`, …) leaves its nodes as they are.
- **The event:** each reload that added or deleted a subtree sends one
  `GeneralModelChangeEventType` event from the Server object (subscribe to events on
  `i=2253`), so that a client that caches the address space browses again.  Its
  `Changes` name each sensor object deleted (Verb `NodeDeleted`, 2) and added
  (`NodeAdded`, 1), AffectedType `ImuSensorType`, then the Sensors folder
  (`ReferenceAdded`, 4, and/or `ReferenceDeleted`, 8, AffectedType FolderType); a
  changed sensor is in it twice, deleted then added.  The nodes below a sensor object
  are not listed one by one.  The gateway's nodes have no `NodeVersion` property.
- **The `opcua:` section changed:** the server is restarted, and its sessions closed.

A sensor of an AH with its methods and an alarm is 92 nodes; removing one and adding
another took 20 to 75 ms of the event loop on the development VM (a restart of the
server, as a reload did before: 1.5 s, every session closed).

**Why some of it is the gateway's own code.** asyncua 2.1's DeleteNodes calls the
callback of each monitored item on a deleted node without awaiting it (a coroutine),
so no client heard anything, and would have sent a StatusChangeNotification for the
whole subscription rather than the item's `BadNodeIdUnknown`; the gateway tells each
item itself before the deletion (`imu_gateway/frontends/opcua/live.py`).
"""
