"""The OPC UA server (docs/opcua.md): asyncua, inside the gateway's event loop.

It reads the cache like every front end: a new reading is written into the address
space once (``write_attribute_value``: asyncua then serves every Read from it and
notifies every monitored item), with the sample's wire time as SourceTimestamp and
the sensor's status as the StatusCode.  No Read waits for the serial bus; commands
(methods) go through the gateway's command path, so through the bus master's queue.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua

from ...cache import EventKind, Snapshot
from ...commands import CATALOGUE, argument_type, commands_for
from ...config import OpcUaConfig, SensorConfig
from ...errors import ErrorKind, StartupError
from ...model import CAPABILITIES, VALUE_GROUPS, Group, WireProtocol
from ...normalise import field_values
from ...stats import FrontendCounts
from ...supervise import Frontend
from ..common import GatewayLike
from .guard import GatewayUaServer
from .history import install as install_history
from .security import ConfigUsers, secure
from .space import BUS_VARS, NAMESPACE, SENSOR_VARS, UNECE, UNITS, quality

log = logging.getLogger("imu_gateway.opcua")

BUS_EVERY_S = 1.0  # how often the bus counters are written

#: How a failed command shows as a method call's StatusCode.
CALL_STATUS = {
    ErrorKind.BAD_ARGUMENTS: "BadInvalidArgument",
    ErrorKind.UNSUPPORTED: "BadNotSupported",
    ErrorKind.BUSY: "BadResourceUnavailable",
    ErrorKind.TIMEOUT: "BadTimeout",
    ErrorKind.OFFLINE: "BadCommunicationError",
    ErrorKind.FAILURE: "BadDeviceFailure",
}


def _status(name: str) -> ua.StatusCode:
    return ua.StatusCode(getattr(ua.StatusCodes, name))


class OpcUaServer(Frontend):
    """The gateway's OPC UA server; ``start()`` listens, ``stop()`` closes."""

    name = "opcua"

    def __init__(self, gateway: GatewayLike, config: OpcUaConfig) -> None:
        super().__init__()
        self.gateway, self.config = gateway, config
        self.server: Server | None = None
        self.certificate: Path | None = None
        self.idx = 0
        self.values: dict[str, list[tuple[str, ua.NodeId]]] = {}  # sensor -> (field, node)
        self.status_nodes: dict[str, list[tuple[Any, ua.NodeId]]] = {}
        self.bus_nodes: dict[str, list[tuple[Any, ua.NodeId]]] = {}
        self.counts: Counter[str] = Counter()
        self._unsubscribe: Any = None
        self._bus_timer: asyncio.Task[None] | None = None

    @property
    def listening(self) -> bool:
        return self.server is not None

    @property
    def port(self) -> int:
        """The port listened on (the one asked for, or the one given for port 0)."""
        if self.server is not None and self.server.bserver is not None:
            return int(self.server.bserver.port)
        return self.config.listen.port

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.config.listen}/"  # (an IPv6 host in brackets)

    def _id(self, path: str) -> ua.NodeId:
        return ua.NodeId(f"{self.gateway.config.gateway_id}.{path}", self.idx)

    def _q(self, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.idx)

    async def start(self) -> None:
        """Build the address space and listen; raises ``OSError`` when the address
        cannot be bound, ``StartupError`` when ``pki_dir`` cannot be used."""
        gid = self.gateway.config.gateway_id
        server = GatewayUaServer(user_manager=ConfigUsers(self.config))
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"imu-gateway {gid}")
        uri = f"urn:imu-gateway:{gid}"
        await server.set_application_uri(uri)
        try:
            self.certificate = await secure(server, self.config, uri)
        except OSError as exc:  # not the port's: the folder of its certificate and key
            raise StartupError(f"opcua.pki_dir {self.config.pki_dir}: {exc.strerror or exc} "
                               "(the gateway keeps its OPC UA certificate and key there, and "
                               "reads the trusted client certificates from it: give it a "
                               "folder it can write)") from None
        self.idx = await server.register_namespace(NAMESPACE)
        await self._build(server)
        await install_history(server, self.gateway.history, {
            node: (s, f) for s, pairs in self.values.items() for f, node in pairs})
        try:
            await server.start()
        except OSError:
            with contextlib.suppress(Exception):
                await server.stop()
            raise
        self.server = server
        for snap in self.gateway.cache.snapshots():
            await self._write_sensor(snap)
        self._unsubscribe = self.gateway.cache.subscribe(self._on_cache_event, self.fail)
        self._bus_timer = asyncio.create_task(self._write_buses(), name="opcua buses")
        self.guarded(self._bus_timer)
        log.info("OPC UA on %s", self.endpoint)

    async def stop(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        if self._bus_timer is not None:
            self._bus_timer.cancel()
        server, self.server = self.server, None
        if server is not None:
            await server.stop()

    # ------------------------------------------------------------ the address space

    async def _build(self, server: Server) -> None:
        gid = self.gateway.config.gateway_id
        top = await server.nodes.objects.add_folder(self._id("IMU Gateway"), self._q("IMU Gateway"))
        gateway = await top.add_folder(self._id(""), self._q(gid))
        sensors = await gateway.add_folder(self._id("Sensors"), self._q("Sensors"))
        protocols = {s.name: b.protocol for b, s in self.gateway.config.iter_sensors()}
        for sensor in self.gateway.sensors.values():
            await self._build_sensor(sensors, sensor, protocols[sensor.name])
        buses = await gateway.add_folder(self._id("Buses"), self._q("Buses"))
        for bus in self.gateway.config.buses:
            node = await buses.add_object(self._id(f"Buses.{bus.name}"), self._q(bus.name))
            self.bus_nodes[bus.name] = [
                (row, (await self._variable(node, f"Buses.{bus.name}.{row.name}", row.name,
                                            row.datatype, row.description)).nodeid)
                for row in BUS_VARS]

    async def _build_sensor(self, parent: Node, sensor: SensorConfig,
                            protocol: WireProtocol) -> None:
        base = f"Sensors.{sensor.name}"
        node = await parent.add_object(self._id(base), self._q(sensor.name))
        self.values[sensor.name] = []
        for group, spec in VALUE_GROUPS.items():
            if group not in CAPABILITIES[sensor.series].groups:
                continue
            folder = await node.add_folder(self._id(f"{base}.{spec.title}"), self._q(spec.title))
            for name in spec.fields:
                item = await self._analog(folder, f"{base}.{spec.title}.{name}", name, group)
                self.values[sensor.name].append((name, item.nodeid))
        self.status_nodes[sensor.name] = [
            (row, (await self._variable(node, f"{base}.{row.name}", row.name, row.datatype,
                                        row.description)).nodeid) for row in SENSOR_VARS]
        for name, value, kind in (("Series", sensor.series.name, "String"),
                                  ("Protocol", protocol.name.lower(), "String"),
                                  ("Address", sensor.address, "UInt16")):
            await self._variable(node, f"{base}.{name}", name, kind, name.lower(), value)
        if self.config.allow_commands:
            await self._methods(node, sensor, protocol)

    async def _variable(self, parent: Node, path: str, name: str, kind: str,
                        description: str, value: Any = None) -> Node:
        node = await parent.add_variable(self._id(path), self._q(name), _variant(value, kind),
                                         datatype=ua.NodeId(getattr(ua.VariantType, kind).value))
        await node.write_attribute(ua.AttributeIds.Description,
                                   ua.DataValue(ua.Variant(ua.LocalizedText(description))))
        return node

    async def _analog(self, parent: Node, path: str, name: str, group: Group) -> Node:
        """An AnalogItemType variable (Float) with its EURange and EngineeringUnits."""
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = self._id(path)
        item.BrowseName = ua.QualifiedName(name, self.idx)
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(ua.ObjectIds.AnalogItemType)
        attrs = ua.VariableAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(f"{name} ({VALUE_GROUPS[group].name})")
        attrs.DataType = ua.NodeId(ua.ObjectIds.Float)
        attrs.Value = _variant(None, "Float")  # until the first reading
        attrs.ValueRank = ua.ValueRank.Scalar
        attrs.AccessLevel = attrs.UserAccessLevel = \
            ua.AccessLevel.CurrentRead.mask | ua.AccessLevel.HistoryRead.mask
        attrs.Historizing = True
        item.NodeAttributes = attrs
        (result,) = await parent.session.add_nodes([item])
        result.StatusCode.check()
        node = Node(parent.session, result.AddedNodeId)
        span = VALUE_GROUPS[group].span
        await node.add_property(0, "EURange", ua.Range(-span, span))
        unit = UNITS[group]
        if unit is not None:
            await node.add_property(0, "EngineeringUnits", ua.EUInformation(
                NamespaceUri=UNECE, UnitId=unit.unit_id, DisplayName=ua.LocalizedText(unit.symbol),
                Description=ua.LocalizedText(unit.name)))
        return node

    async def _methods(self, node: Node, sensor: SensorConfig, protocol: WireProtocol) -> None:
        """The catalogue's commands of this series and protocol, as methods: one input
        argument (or none), a result string out."""
        have = commands_for(sensor.series, protocol)
        for spec in CATALOGUE.values():
            if spec.name not in have:
                continue
            inputs = []
            if spec.argument is not None:
                kind = {str: "String", int: "Int32"}.get(argument_type(spec) or float, "Double")
                arg = ua.Argument(Name=spec.argument,
                                  DataType=ua.NodeId(getattr(ua.ObjectIds, kind)),
                                  ValueRank=-1, Description=ua.LocalizedText(spec.summary))
                inputs.append(arg)
            result = ua.Argument(Name="result", DataType=ua.NodeId(ua.ObjectIds.String),
                                 ValueRank=-1)
            path = f"Sensors.{sensor.name}.{spec.name}"
            await node.add_method(self._id(path), self._q(spec.name),
                                  self._caller(sensor.name, spec.name, spec.argument),
                                  inputs, [result])

    def _caller(self, sensor: str, command: str, argument: str | None) -> Any:
        async def call(parent: ua.NodeId, *args: ua.Variant) -> Any:
            self.counts["calls"] += 1
            values = {argument: args[0].Value} if argument is not None and args else {}
            result = await self.gateway.command(sensor, command, values)
            if not result.ok:
                self.counts["call_errors"] += 1
                # (a StatusCode returned is the call's; an exception would be asyncua's
                # BadUnexpectedError, whatever it said)
                return _status(CALL_STATUS.get(result.kind or ErrorKind.FAILURE,
                                               "BadInternalError"))
            return [ua.Variant(f"{command}: ok {dict(result.answer)}", ua.VariantType.String)]
        return call

    # ------------------------------------------------------------ values

    def _on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is not EventKind.SETTINGS and self.server is not None:
            task = asyncio.create_task(self._write_sensor(snap))
            task.add_done_callback(self._written)

    def _written(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            self.fail(task.exception())  # type: ignore[arg-type]

    async def _write_sensor(self, snap: Snapshot) -> None:
        server = self.server
        if server is None or snap.name not in self.values:
            return
        now = datetime.now(UTC)
        source = snap.timestamp or now
        code = _status(quality(snap))
        fields = field_values(snap.reading) if snap.reading is not None else {}
        for name, nodeid in self.values[snap.name]:
            await server.write_attribute_value(nodeid, ua.DataValue(
                _variant(fields.get(name), "Float"), StatusCode=code, SourceTimestamp=source,
                ServerTimestamp=now))
        for row, nodeid in self.status_nodes[snap.name]:
            await server.write_attribute_value(nodeid, ua.DataValue(
                _variant(row.value(snap), row.datatype), SourceTimestamp=source,
                ServerTimestamp=now))
        self.counts["samples"] += 1

    async def _write_buses(self) -> None:
        while True:
            server = self.server
            if server is not None:
                now = datetime.now(UTC)
                for bus in self.gateway.stats():
                    for row, nodeid in self.bus_nodes.get(bus.name, []):
                        await server.write_attribute_value(nodeid, ua.DataValue(
                            _variant(row.value(bus), row.datatype), SourceTimestamp=now,
                            ServerTimestamp=now))
            await asyncio.sleep(BUS_EVERY_S)

    def stats(self) -> FrontendCounts:
        sessions = 0
        if self.server is not None:
            sessions = len(getattr(self.server.iserver, "asyncio_transports", []))
        return {"clients": sessions, "requests": self.counts["calls"],
                "samples": self.counts["samples"], "call_errors": self.counts["call_errors"]}


def _variant(value: Any, kind: str) -> Any:
    """A Variant of the named type.  A missing number is NaN, under a Bad or Uncertain
    StatusCode that says why (asyncua refuses a null Variant for a typed variable)."""
    if value is None:
        value = math.nan if kind in ("Float", "Double") else ""
    return ua.Variant(value, getattr(ua.VariantType, kind))
