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
