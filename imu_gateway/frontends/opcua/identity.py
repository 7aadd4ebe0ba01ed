"""What the server says of itself: BuildInfo, ServerCapabilities and the history
capabilities, one row per node of the standard address space (OPC UA Part 5, 6.3.1
and 6.3.2).  asyncua leaves most of them null and names itself "FreeOpcUa Python
Server 1.0pre"; an integrator's client reads these first.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Server, ua

from ... import __version__
from .guard import MAX_SUBSCRIPTIONS_PER_SESSION

PRODUCT_NAME = "imu-gateway"
PRODUCT_URI = "urn:imu-gateway:product"
MANUFACTURER = "the imu-gateway project"
LOCALES = ["en"]
#: The profiles (Part 7) whose facets the server implements; claimed by their URIs,
#: not certified (no conformance test tool has run on it).
PROFILES = [
    "http://opcfoundation.org/UA-Profile/Server/MicroEmbeddedDevice2017",
    "http://opcfoundation.org/UA-Profile/Server/Methods",
    "http://opcfoundation.org/UA-Profile/Server/HistoricalRawData",
    "http://opcfoundation.org/UA-Profile/Server/AggregateHistorical",
]
#: 0: no limit (Part 5): a history continuation point holds where the next page starts,
#: the server keeps nothing for it
MAX_HISTORY_CONTINUATIONS = 0


@dataclass(frozen=True, slots=True)
class Capability:
    node: int  # ObjectIds
    value: Any
    kind: ua.VariantType


def build_date() -> datetime:
    """When the installed package was built: its files' time (a wheel's install keeps
    the time they were packed; a checkout's, the last edit)."""
    return datetime.fromtimestamp(Path(__file__).stat().st_mtime, UTC)


def capabilities(server: Server) -> list[Capability]:
    limits = server.limits
    v, o = ua.VariantType, ua.ObjectIds
    return [
        Capability(o.Server_ServerCapabilities_ServerProfileArray, PROFILES, v.String),
        Capability(o.Server_ServerCapabilities_LocaleIdArray, LOCALES, v.String),
        # the cache writes each sample once; a monitored item is sampled on that write
        Capability(o.Server_ServerCapabilities_MinSupportedSampleRate, 0.0, v.Double),
        # browse answers whole (asyncua keeps no browse or query continuation points)
        Capability(o.Server_ServerCapabilities_MaxBrowseContinuationPoints, 0, v.UInt16),
        Capability(o.Server_ServerCapabilities_MaxQueryContinuationPoints, 0, v.UInt16),
        Capability(o.Server_ServerCapabilities_MaxHistoryContinuationPoints,
                   MAX_HISTORY_CONTINUATIONS, v.UInt16),
        Capability(o.Server_ServerCapabilities_SoftwareCertificates, [],
                   v.ExtensionObject),
        Capability(o.Server_ServerCapabilities_MaxArrayLength, 0, v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxStringLength, limits.max_message_size,
                   v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxByteStringLength,
                   limits.max_message_size, v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxSessions,
                   server.iserver.max_connections, v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxSubscriptions,
                   server.iserver.max_subscriptions, v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxSubscriptionsPerSession,
                   MAX_SUBSCRIPTIONS_PER_SESSION, v.UInt32),
        # (0: no limit of its own; a Publish answers what the queue holds)
        Capability(o.Server_ServerCapabilities_MaxMonitoredItems, 0, v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxMonitoredItemsPerSubscription, 0, v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxMonitoredItemsQueueSize, 0, v.UInt32),
        # events are not served: no select or where clause is taken
        Capability(o.Server_ServerCapabilities_MaxSelectClauseParameters, 0, v.UInt32),
        Capability(o.Server_ServerCapabilities_MaxWhereClauseParameters, 0, v.UInt32),
        Capability(o.Server_ServerCapabilities_ConformanceUnits, [], v.QualifiedName),
        Capability(o.Server_Auditing, False, v.Boolean),
        # history: what it offers is history.install's to say; what it does not, here
        Capability(o.HistoryServerCapabilities_AccessHistoryEventsCapability, False,
                   v.Boolean),
        Capability(o.HistoryServerCapabilities_MaxReturnEventValues, 0, v.UInt32),
        *(Capability(node, False, v.Boolean) for node in (
            o.HistoryServerCapabilities_InsertDataCapability,
            o.HistoryServerCapabilities_ReplaceDataCapability,
            o.HistoryServerCapabilities_UpdateDataCapability,
            o.HistoryServerCapabilities_DeleteRawCapability,
            o.HistoryServerCapabilities_DeleteAtTimeCapability,
            o.HistoryServerCapabilities_InsertEventCapability,
            o.HistoryServerCapabilities_ReplaceEventCapability,
            o.HistoryServerCapabilities_UpdateEventCapability,
            o.HistoryServerCapabilities_DeleteEventCapability,
            o.HistoryServerCapabilities_InsertAnnotationCapability)),
    ]


async def describe(server: Server) -> None:
    """Write the gateway's BuildInfo and capabilities into ``server``'s standard nodes
    (after ``init``, before ``start``); the history's are ``history.install``'s."""
    await server.set_build_info(PRODUCT_URI, MANUFACTURER, PRODUCT_NAME, __version__,
                                __version__, build_date())
    for row in capabilities(server):
        node = server.get_node(ua.NodeId(row.node))
        await node.write_value(ua.Variant(row.value, row.kind))
