"""The address space's nodes: the ``ImuSensorType`` ObjectType and each sensor as an
instance of it, built by one function from the rows of ``space``.

Every node the gateway adds has a string NodeId in the gateway's namespace, the path
of browse names below its root joined by dots (``ImuSensorType.Angles.pitch.EURange``,
``{gateway_id}.Sensors.boom.Angles.pitch.EURange``): stable across restarts and
reordered configs, and never mixed in with namespace 0's numeric ids.

The type declares what a sensor may have (OPC UA Part 3, 6.4.4): the value groups every
series measures, the status variables and the identity are Mandatory; the groups only
some series measure, and every method, are Optional.  An instance is built by the same
function with the groups and methods of its series, so a client's template (a SCADA's
UDT) made from the type fits each sensor.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from asyncua import Node, ua

from ...commands import CommandSpec
from ...model import CAPABILITIES, VALUE_GROUPS, Group, Series
from .methods import Caller, input_arguments
from .space import IDENTITY_VARS, SENSOR_VARS, UNECE, UNITS

TYPE_NAME = "ImuSensorType"
#: The folder of a sensor's alarm conditions.
ALARMS = "Alarms"
#: The groups every series measures: Mandatory in the type; the others are Optional.
COMMON_GROUPS = frozenset(g for g in Group if all(g in CAPABILITIES[s].groups for s in Series))
#: The VariantType of every measured and derived value.
VALUE_TYPE = "Double"
#: What a measured value's access level says: read now, and read its history.
VALUE_ACCESS = ua.AccessLevel.CurrentRead.mask | ua.AccessLevel.HistoryRead.mask
#: A method's caller, made for its command once the node it belongs to is known.
Callers = Callable[[CommandSpec, ua.NodeId], Caller]


@dataclass(frozen=True, slots=True)
class Ids:
    """The NodeIds under one root: ``{root}.{path}`` in namespace ``ns``."""

    root: str
    ns: int

    def __call__(self, path: str = "") -> ua.NodeId:
        return ua.NodeId(f"{self.root}.{path}" if path else self.root, self.ns)

    def name(self, name: str) -> ua.QualifiedName:
        return ua.QualifiedName(name, self.ns)


@dataclass(slots=True)
class Built:
    """What an instance's writers need: its value and status variables' NodeIds."""

    values: list[tuple[str, ua.NodeId]]  # (field, node)
    status: list[tuple[Any, ua.NodeId]]  # (SensorVar row, node)


async def add_node(parent: Node, nodeid: ua.NodeId, name: ua.QualifiedName,
                   nodeclass: ua.NodeClass, typedef: int | ua.NodeId, attrs: Any,
                   reference: int = ua.ObjectIds.HasComponent) -> Node:
    """One AddNodes item.  (asyncua's ``add_object`` with a type would instantiate the
    type's children itself, with ids of its own choosing.)"""
    item = ua.AddNodesItem()
    item.RequestedNewNodeId = nodeid
    item.BrowseName = name
    item.NodeClass = nodeclass
    item.ParentNodeId = parent.nodeid
    item.ReferenceTypeId = ua.NodeId(reference)
    item.TypeDefinition = typedef if isinstance(typedef, ua.NodeId) else ua.NodeId(typedef)
    attrs.DisplayName = ua.LocalizedText(name.Name)
    item.NodeAttributes = attrs
    (result,) = await parent.session.add_nodes([item])
    result.StatusCode.check()
    return Node(parent.session, result.AddedNodeId)


async def build_type(base: Node, ns: int, commands: Iterable[CommandSpec],
                     caller: Callers) -> ua.NodeId:
    """``ImuSensorType`` under BaseObjectType, with every part a sensor may have."""
    ids = Ids(TYPE_NAME, ns)
    attrs = ua.ObjectTypeAttributes()
    attrs.Description = ua.LocalizedText("An IMU, VG, AH or MINS sensor on a serial line "
                                         "of the gateway")
    sensor_type = await add_node(base, ids(), ids.name(TYPE_NAME), ua.NodeClass.ObjectType,
                                 ua.NodeId(), attrs, ua.ObjectIds.HasSubtype)
    await add_parts(sensor_type, ids, set(Group), {}, commands, caller)
    # the alarms' conditions (conditions.py): every sensor has at least its
    # communication alarm
    alarms = await sensor_type.add_folder(ids(ALARMS), ids.name(ALARMS))
    await alarms.set_modelling_rule(True)
    return sensor_type.nodeid


async def build_sensor(parent: Node, ids: Ids, name: str, type_id: ua.NodeId,
                       groups: set[Group], identity: dict[str, Any],
                       commands: Iterable[CommandSpec], caller: Callers) -> Built:
    """One sensor: an ImuSensorType object with its series' groups and methods, its
    identity variables written (``identity``: by name)."""
    attrs = ua.ObjectAttributes()
    attrs.Description = ua.LocalizedText(f"sensor {name}")
    node = await add_node(parent, ids(), ids.name(name), ua.NodeClass.Object, type_id, attrs,
                          ua.ObjectIds.Organizes)
    return await add_parts(node, ids, groups, identity, commands, caller)


async def add_parts(node: Node, ids: Ids, groups: set[Group], identity: dict[str, Any],
                    commands: Iterable[CommandSpec], caller: Callers) -> Built:
    """The value groups, status and identity variables and methods of a sensor under
    ``node``.  Under the type (``node`` an ObjectType) they are its declarations, each
    with its modelling rule."""
    declare = await node.read_node_class() == ua.NodeClass.ObjectType
    built = Built([], [])
    for group, spec in VALUE_GROUPS.items():
        if group not in groups:
            continue
        folder = await node.add_folder(ids(spec.title), ids.name(spec.title))
        if declare:
            await folder.set_modelling_rule(group in COMMON_GROUPS)
        for field in spec.fields:
            item = await _analog(folder, ids, f"{spec.title}.{field}", field, group, declare)
            built.values.append((field, item.nodeid))
    for row in SENSOR_VARS:
        var = await _variable(node, ids, row.name, row.datatype, row.description, declare)
        built.status.append((row, var.nodeid))
    for ident in IDENTITY_VARS:
        await _variable(node, ids, ident.name, ident.datatype, ident.description, declare,
                        identity.get(ident.name))
    for command in commands:
        method = await add_method(node, ids, command, caller(command, node.nodeid))
        if declare:
            await method.set_modelling_rule(False)
    return built


async def _variable(parent: Node, ids: Ids, name: str, kind: str, description: str,
                    declare: bool, value: Any = None) -> Node:
    node = await parent.add_variable(ids(name), ids.name(name), variant(value, kind),
                                     datatype=ua.NodeId(getattr(ua.VariantType, kind).value))
    if declare:
        await node.set_modelling_rule(True)
    await node.write_attribute(ua.AttributeIds.Description,
                               ua.DataValue(ua.Variant(ua.LocalizedText(description))))
    return node


async def _analog(parent: Node, ids: Ids, path: str, name: str, group: Group,
                  declare: bool) -> Node:
    """An AnalogItemType variable (Double: a sensor's 32.52 reads 32.52, where a Float
    would widen to 32.52000045776367 in the client) with its EURange and
    EngineeringUnits, its history readable (docs/opcua.md, "History")."""
    attrs = ua.VariableAttributes()
    attrs.Description = ua.LocalizedText(f"{name} ({VALUE_GROUPS[group].name})")
    attrs.DataType = ua.NodeId(ua.ObjectIds.Double)
    attrs.Value = variant(None, VALUE_TYPE)  # until the first reading
    attrs.ValueRank = ua.ValueRank.Scalar
    attrs.AccessLevel = attrs.UserAccessLevel = VALUE_ACCESS
    attrs.Historizing = True
    node = await add_node(parent, ids(path), ids.name(name), ua.NodeClass.Variable,
                          ua.ObjectIds.AnalogItemType, attrs)
    if declare:
        await node.set_modelling_rule(True)
    span = VALUE_GROUPS[group].span
    properties: list[tuple[str, Any, int]] = [
        ("EURange", ua.Range(-span, span), ua.ObjectIds.Range)]
    unit = UNITS[group]
    if unit is not None:
        properties.append(("EngineeringUnits", ua.EUInformation(
            NamespaceUri=UNECE, UnitId=unit.unit_id, DisplayName=ua.LocalizedText(unit.symbol),
            Description=ua.LocalizedText(unit.name)), ua.ObjectIds.EUInformation))
    for prop, value, datatype in properties:
        made = await node.add_property(ids(f"{path}.{prop}"), ua.QualifiedName(prop, 0), value,
                                       datatype=ua.NodeId(datatype))
        if declare:
            await made.set_modelling_rule(True)
    return node


async def add_method(node: Node, ids: Ids, spec: CommandSpec, call: Caller) -> Node:
    """A command as a method: its one argument (or none) in, a ``result`` string out."""
    result = ua.Argument(Name="result", DataType=ua.NodeId(ua.ObjectIds.String),
                         ValueRank=-1, Description=ua.LocalizedText("what the sensor answered"))
    made: Node = await node.add_method(ids(spec.name), ids.name(spec.name), call,
                                       input_arguments(spec), [result])
    return made


def variant(value: Any, kind: str) -> ua.Variant:
    """A Variant of the named type.  A missing number is NaN, under a Bad or Uncertain
    StatusCode that says why (asyncua refuses a null Variant for a typed variable)."""
    if value is None:
        value = float("nan") if kind in ("Float", "Double") else ""
    return ua.Variant(value, getattr(ua.VariantType, kind))

