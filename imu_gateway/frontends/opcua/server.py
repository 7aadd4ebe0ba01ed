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
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua

from ...cache import ALL_EVENTS, EventKind, Snapshot
from ...commands import CATALOGUE, CommandSpec, commands_for
from ...config import OpcUaConfig
from ...derived import values_of
from ...errors import ErrorKind, StartupError
from ...model import CAPABILITIES
from ...stats import FrontendCounts
from ...supervise import Frontend, RepeatFilter
from ..common import GatewayLike
from . import encoding, standard_space
from .conditions import Conditions
from .guard import MAX_SUBSCRIPTIONS_PER_SESSION, GatewayUaServer
from .history import GatewayHistory
from .history import install as install_history
from .identity import MANUFACTURER, PRODUCT_URI, describe
from .live import ModelChange, Shape, Verb, model_change_event, retire
from .methods import Caller, instance_caller, type_caller
from .nodes import VALUE_TYPE, Callers, Ids, build_sensor, build_type, variant
from .security import ConfigUsers, secure
from .space import BUS_VARS, NAMESPACE, quality
from .writes import DirectWriter, Due, Samples, SensorNodes, Which, tell

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
    ErrorKind.UNCONFIRMED: "BadDeviceFailure",  # as Modbus TCP's 04: read it back
}


#: asyncua's loggers that log once per request or connection at WARNING or above
#: (a service fault, a refused connection, a session closed): a line a minute each.
ASYNCUA_PER_REQUEST = ("asyncua.server.uaprocessor", "asyncua.server.binary_server_asyncio",
                       "asyncua.server.internal_session", "asyncua.server.internal_server",
                       "asyncua.server.address_space", "asyncua.common.connection",
                       "asyncua.uaprotocol")


#: Clients at once (asyncua's 1000 is near a process's 1024 descriptors, which every
#: front end and port shares), and how long a connection may stay without an
#: activated session (asyncua: 30 s).
MAX_CLIENTS, ACTIVATION_S = 100, 10.0


def limit_clients(server: Server) -> None:
    server.iserver.max_connections = MAX_CLIENTS
    server.iserver.max_pending_activation_seconds = ACTIVATION_S
    server.iserver.max_subscriptions = MAX_CLIENTS * MAX_SUBSCRIPTIONS_PER_SESSION


def quiet_asyncua() -> None:
    """asyncua logs about a thousand INFO lines at each start and one per Publish: at
    the gateway's default level it says only its warnings, each at most once a
    minute.  With ``--log-level debug`` it says everything."""
    if logging.getLogger("imu_gateway").getEffectiveLevel() <= logging.DEBUG:
        return
    logging.getLogger("asyncua").setLevel(logging.WARNING)
    for name in ASYNCUA_PER_REQUEST:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RepeatFilter) for f in logger.filters):
            logger.addFilter(RepeatFilter())


def _status(name: str) -> ua.StatusCode:
    return ua.StatusCode(getattr(ua.StatusCodes, name))


class Sample(ua.DataValue):  # type: ignore[misc]  # (asyncua is untyped here)
    """A DataValue the gateway writes and never changes afterwards (a new one for each
    sample), of an immutable number or string: its own deep copy.  asyncua deep-copies
    the value of every write once per monitored item of the node (so that a value
    changed in place later is still told apart from the old one); for the gateway's
    values that copy is an identical object, and ``copy.deepcopy`` of a DataValue was
    the largest cost of a sample with a subscriber (docs/benchmarks.md, "CPU per sample
    in the front ends")."""

    __slots__ = ()

    def __deepcopy__(self, memo: dict[int, Any]) -> Sample:
        return self


class OpcUaServer(Frontend):
    """The gateway's OPC UA server; ``start()`` listens, ``stop()`` closes."""

    name = "opcua"

    def __init__(self, gateway: GatewayLike, config: OpcUaConfig) -> None:
        super().__init__()
        self.gateway, self.config = gateway, config
        self.server: GatewayUaServer | None = None
        self.certificate: Path | None = None
        self.idx = 0
        self.nodes = SensorNodes()  # each sensor's value and status nodes
        self.bus_nodes: dict[str, list[tuple[Any, ua.NodeId]]] = {}
        self.callers: dict[tuple[ua.NodeId, str], Caller] = {}  # (object, command)
        self.counts: Counter[str] = Counter()
        self._unsubscribe: Any = None
        self._bus_timer: asyncio.Task[None] | None = None
        self._events: asyncio.Task[None] | None = None
        self.conditions = Conditions(gateway, config.allow_commands)
        self.shapes: dict[str, Shape] = {}  # sensor -> what its subtree was built from
        self._history: GatewayHistory | None = None
        self._writer: DirectWriter  # (with the server, at start)
        self._samples: Samples  # (likewise)
        self._sensors: Node | None = None  # the Sensors folder
        self._type_id = ua.NodeId()  # ImuSensorType's
        self._changing = asyncio.Lock()  # one reload's changes at a time

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

    async def start(self) -> None:
        """Build the address space and listen; raises ``OSError`` when the address
        cannot be bound, ``StartupError`` when ``pki_dir`` cannot be used."""
        gid = self.gateway.config.gateway_id
        quiet_asyncua()
        encoding.install()
        server = GatewayUaServer(user_manager=ConfigUsers(self.config),
                                 catch_up=self._catch_up)
        await server.init(await standard_space.shelf())
        server.set_endpoint(self.endpoint)
        server.set_server_name(f"imu-gateway {gid}")
        server.product_uri, server.manufacturer_name = PRODUCT_URI, MANUFACTURER
        limit_clients(server)
        await describe(server)
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
        self._history = await install_history(server, self.gateway.history, {
            node: (s, f) for s, pairs in self.nodes.values.items() for f, node in pairs})
        try:
            await server.start()
        except OSError:
            with contextlib.suppress(Exception):
                await server.stop()
            raise
        self.server = server
        self._writer = DirectWriter(server.iserver.aspace)
        self._samples = Samples(self._write_sensor, server.watch.every, self.nodes.pairs,
                                self.fail)
        for snap in self.gateway.cache.snapshots():
            await tell(self._write_sensor(snap))
        # not prompt: its clients read, publish and sample at their own times, and each
        # of those catches the cache up first (``guard.Watch.catch_up``)
        self._unsubscribe = self.gateway.cache.subscribe(self._on_cache_event, self.fail,
                                                         kinds=ALL_EVENTS, prompt=False)
        self._events = asyncio.create_task(self.conditions.run(), name="opcua alarm events")
        self.guarded(self._events)
        self._bus_timer = asyncio.create_task(self._write_buses(), name="opcua buses")
        self.guarded(self._bus_timer)
        log.info("OPC UA on %s", self.endpoint)

    async def stop(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        for task in (self._bus_timer, self._events):
            if task is not None:
                task.cancel()
        server, self.server = self.server, None
        if server is not None:
            await server.stop()

    # ------------------------------------------------------------ the address space

    async def _build(self, server: Server) -> None:
        gid = self.gateway.config.gateway_id
        ids = Ids(gid, self.idx)
        top = await server.nodes.objects.add_folder(ids("IMU Gateway"), ids.name("IMU Gateway"))
        gateway = await top.add_folder(ids(), ids.name(gid))
        self._sensors = await gateway.add_folder(ids("Sensors"), ids.name("Sensors"))
        self._type_id = await build_type(server.nodes.base_object_type, self.idx,
                                         self._commands,
                                         lambda spec, _: type_caller(spec, self.callers))
        await self.conditions.build(server, gateway)
        for name in self.gateway.sensors:
            await self._add_sensor(server, name)
        buses = await gateway.add_folder(ids("Buses"), ids.name("Buses"))
        for bus in self.gateway.config.buses:
            bus_ids = Ids(f"{gid}.Buses.{bus.name}", self.idx)
            node = await buses.add_object(bus_ids(), bus_ids.name(bus.name))
            self.bus_nodes[bus.name] = []
            for row in BUS_VARS:
                var = await node.add_variable(bus_ids(row.name), bus_ids.name(row.name),
                                              variant(None, row.datatype),
                                              datatype=ua.NodeId(getattr(ua.VariantType,
                                                                         row.datatype).value))
                await var.write_attribute(ua.AttributeIds.Description, ua.DataValue(
                    ua.Variant(ua.LocalizedText(row.description))))
                self.bus_nodes[bus.name].append((row, var.nodeid))

    @property
    def _commands(self) -> list[CommandSpec]:
        return list(CATALOGUE.values()) if self.config.allow_commands else []

    def _ids(self, sensor: str) -> Ids:
        return Ids(f"{self.gateway.config.gateway_id}.Sensors.{sensor}", self.idx)

    def _shape(self, sensor: str) -> Shape:
        """What the sensor's subtree is built from, in the config now."""
        config = self.gateway.sensors[sensor]
        protocol = next(b.protocol for b, s in self.gateway.config.iter_sensors()
                        if s.name == sensor)
        have = commands_for(config.series, protocol)
        return Shape(config.series.name, protocol.name.lower(),
                     tuple(c.name for c in self._commands if c.name in have),
                     tuple(a.row(sensor) for a in config.alarms))

    async def _add_sensor(self, server: Server, name: str) -> ua.NodeId:
        """One sensor's subtree (values, status, identity, methods, conditions) and its
        history; returns its object's NodeId."""
        sensor, shape = self.gateway.sensors[name], self._shape(name)
        ids = self._ids(name)
        built = await build_sensor(
            self._sensors, ids, name, self._type_id, set(CAPABILITIES[sensor.series].groups),
            {"Series": shape.series, "Protocol": shape.protocol, "Address": sensor.address},
            [c for c in self._commands if c.name in shape.commands], self._method_of(name))
        self.nodes.add(name, built.values, built.status)
        self.shapes[name] = shape
        inputs = {**dict(built.values), **{row.name: node for row, node in built.status}}
        await self.conditions.add_sensor(name, server.get_node(ids()), inputs, self.idx,
                                         self.gateway.config.gateway_id)
        if self._history is not None:
            self._history.variables.update({node: (name, f) for f, node in built.values})
        return ids()

    async def _remove_sensor(self, server: Server, name: str) -> None:
        """A sensor's subtree gone: its writes stop at once, its methods and conditions
        are forgotten, its monitored items are told ``BadNodeIdUnknown``."""
        root = self._ids(name)()
        self._samples.forget(name)
        values = self.nodes.remove(name)
        self.shapes.pop(name, None)
        for key in [k for k in self.callers if k[0] == root]:
            del self.callers[key]
        self.conditions.remove_sensor(name, root)
        if self._history is not None:
            for _, node in values:
                self._history.variables.pop(node, None)
        await retire(server, server.get_node(root))
        server.watch.every.changed()  # (its items take no value now: ``every_value``)

    async def sensors_changed(self) -> None:
        """A reload changed the sensors (docs/opcua.md, "A reload"): a sensor added
        gets its subtree, one removed loses it, one whose subtree's makings changed
        (``Shape``) is rebuilt, one whose address changed has it written.  Sessions,
        subscriptions and the other sensors' nodes stay; one GeneralModelChangeEvent
        tells the clients."""
        server, folder = self.server, self._sensors
        if server is None or folder is None:  # (not started: ``start`` builds it then)
            return
        async with self._changing:
            wanted = self.gateway.sensors
            changes: list[ModelChange] = []
            for name in list(self.shapes):
                if name not in wanted or self.shapes[name] != self._shape(name):
                    await self._remove_sensor(server, name)
                    changes.append(ModelChange(self._ids(name)(), self._type_id,
                                               Verb.NODE_DELETED))
            for name, sensor in wanted.items():
                if name in self.shapes:
                    await server.write_attribute_value(self._ids(name)("Address"), ua.DataValue(
                        variant(sensor.address, "UInt16")))
                    continue
                changes.append(ModelChange(await self._add_sensor(server, name), self._type_id,
                                           Verb.NODE_ADDED))
                await tell(self._write_sensor(self.gateway.cache.snapshot(name)))
            if changes:
                verbs = Verb(0)
                for change in changes:
                    verbs |= Verb.REFERENCE_ADDED if change.verb is Verb.NODE_ADDED \
                        else Verb.REFERENCE_DELETED
                changes.append(ModelChange(folder.nodeid,
                                           ua.NodeId(ua.ObjectIds.FolderType), verbs))
                await self.conditions.send(model_change_event(changes),
                                           [ua.NodeId(ua.ObjectIds.Server)])
                log.info("opcua: the address space follows the reload: %s", ", ".join(
                    f"{'+' if c.verb is Verb.NODE_ADDED else '-'}{c.affected.Identifier}"
                    for c in changes[:-1]))

    def _method_of(self, sensor: str) -> Callers:
        def make(spec: CommandSpec, object_id: ua.NodeId) -> Caller:
            async def run(args: dict[str, Any]) -> Any:
                return await self._run(sensor, spec.name, args)
            caller = instance_caller(spec, object_id, run)
            self.callers[(object_id, spec.name)] = caller
            return caller
        return make

    async def _run(self, sensor: str, command: str, args: dict[str, Any]) -> Any:
        """A checked call, through the gateway's command path (so the bus master's
        queue): the result string, or the StatusCode of why there is none."""
        self.counts["calls"] += 1
        result = await self.gateway.command(sensor, command, args)
        if not result.ok:
            self.counts["call_errors"] += 1
            # (a StatusCode returned is the call's; an exception would be asyncua's
            # BadUnexpectedError, whatever it said)
            return _status(CALL_STATUS.get(result.kind or ErrorKind.FAILURE, "BadInternalError"))
        return [ua.Variant(f"{command}: ok {dict(result.answer)}", ua.VariantType.String)]

    # ------------------------------------------------------------ values

    def _on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.ALARM:
            if snap.alarm is not None:
                self.conditions.on_alarm(snap.alarm)
        elif kind is not EventKind.SETTINGS and self.server is not None:
            self.counts["samples"] += 1
            self._samples.offer(snap)  # written now, or when a client looks

    def _catch_up(self) -> None:
        """A client looks (a request, a publish, a sampling tick): the bus's turns
        into the cache, and the newest samples into the address space."""
        self.gateway.cache.catch_up()
        if self.server is not None:
            self._samples.flush()

    def _write_sensor(self, snap: Snapshot, which: Which = None) -> list[Due]:
        """The sample into its sensor's nodes (``which``: None, all), now (``writes``);
        returns the monitored items' callbacks it is due to."""
        due: list[Due] = []
        if self.server is None or snap.name not in self.nodes.values:
            return due
        now = datetime.now(UTC)
        source = snap.timestamp or now
        code = _status(quality(snap))
        fields = values_of(snap)
        write = self._writer.write
        values, status = self.nodes.part(snap.name, which)
        for name, nodeid in values:
            write(nodeid, Sample(variant(fields.get(name), VALUE_TYPE), StatusCode=code,
                                 SourceTimestamp=source, ServerTimestamp=now), due)
        for row, nodeid in status:
            write(nodeid, Sample(variant(row.value(snap), row.datatype),
                                 SourceTimestamp=source, ServerTimestamp=now), due)
        return due

    async def _write_buses(self) -> None:
        while True:
            server = self.server
            if server is not None:
                now = datetime.now(UTC)
                for bus in self.gateway.stats():
                    for row, nodeid in self.bus_nodes.get(bus.name, []):
                        await server.write_attribute_value(nodeid, ua.DataValue(
                            variant(row.value(bus), row.datatype), SourceTimestamp=now,
                            ServerTimestamp=now))
                server.watch.peers.flush_due()
            await asyncio.sleep(BUS_EVERY_S)

    def stats(self) -> FrontendCounts:
        sessions = 0
        if self.server is not None:
            sessions = len(getattr(self.server.iserver, "asyncio_transports", []))
        return {"clients": sessions, "requests": self.counts["calls"],
                "samples": self.counts["samples"], "call_errors": self.counts["call_errors"]}


