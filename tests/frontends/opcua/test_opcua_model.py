"""What an integrator's OPC UA client reads first, with asyncua's client: the server's
BuildInfo and capabilities, the ``ImuSensorType`` a SCADA builds its template on, node
ids that are strings in the gateway's namespace, and methods that refuse a call of the
wrong shape (docs/opcua.md).  Expected names come from the docs and the package, not
from the server."""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua
from support.harness import free_port, running, until

import imu_gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "ua-model"
NS = "urn:imu-gateway"
PASSWORD = "m0del"


class Rig:
    def __init__(self, ah: SimSensor, vg: SimSensor, imu: SimSensor, native: str,
                 modbus: str) -> None:
        self.ah, self.vg, self.imu, self.native, self.modbus = ah, vg, imu, native, modbus

    def config(self, port: int, pki: Path, **opcua: Any) -> dict[str, Any]:
        def line(name: str, path: str, protocol: str, *sensors: dict[str, Any]
                 ) -> dict[str, Any]:
            return {"name": name, "port": path, "baudrate": 115200, "protocol": protocol,
                    "timeout_ms": 300, "sensors": list(sensors)}

        return {"gateway_id": GID,
                "buses": [line("a", self.native, "native",
                               {"name": "boom", "series": "AH", "poll_hz": 10},
                               {"name": "base", "series": "IMU", "address": 1, "poll_hz": 10}),
                          line("b", self.modbus, "modbus",
                               {"name": "mast", "series": "VG", "address": 1, "poll_hz": 10})],
                "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": str(pki),
                          "allow_none": True, **opcua}}


@pytest.fixture
def rig() -> Iterator[Rig]:
    sample = hold(Motion.from_seed(5).sample(2.0))
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=sample)
    imu = make_sensor(WireProtocol.NATIVE, Series.IMU, 1, baud=115200, source=sample)
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=115200, source=sample)
    with simulated([ah, imu]) as a, simulated([vg]) as b:
        yield Rig(ah, vg, imu, a.path, b.path)


@asynccontextmanager
async def served(rig: Rig, pki: Path) -> AsyncIterator[tuple[Client, int]]:
    """The gateway with its first sample in, and asyncua's client on it (security mode
    None): the client and the gateway's namespace index."""
    port = free_port()
    async with running(rig.config(port, pki)) as gw, \
            Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        yield client, await client.get_namespace_index(NS)


async def walk(node: Node) -> AsyncIterator[Node]:
    """Every node below ``node`` by hierarchical references (each once)."""
    seen: set[ua.NodeId] = set()
    todo = [node]
    while todo:
        here = todo.pop()
        for child in await here.get_children():
            if child.nodeid not in seen:
                seen.add(child.nodeid)
                todo.append(child)
                yield child


@pytest.mark.anyio
async def test_build_info_and_capabilities_are_the_gateways(rig: Rig, tmp_path: Path) -> None:
    async with served(rig, tmp_path / "pki") as (client, _):
        build = await client.get_node(ua.ObjectIds.Server_ServerStatus_BuildInfo).read_value()
        assert build.ProductName == "imu-gateway"
        assert build.SoftwareVersion == imu_gateway.__version__
        assert build.BuildNumber and build.ProductUri.startswith("urn:imu-gateway")
        assert "FreeOpcUa" not in f"{build.ManufacturerName} {build.ProductName}"
        assert build.BuildDate.year >= 2024
        nulls = []
        for folder in (ua.ObjectIds.Server_ServerCapabilities,
                       ua.ObjectIds.HistoryServerCapabilities):
            for child in await client.get_node(folder).get_children():
                if await child.read_node_class() != ua.NodeClass.Variable:
                    continue
                value = await child.read_data_value(raise_on_bad_status=False)
                if value.Value is None or value.Value.Value is None:
                    nulls.append((await child.read_browse_name()).Name)
        assert not nulls, f"null capabilities: {nulls}"
        caps = client.get_node(ua.ObjectIds.Server_ServerCapabilities)
        profiles = await (await caps.get_child("0:ServerProfileArray")).read_value()
        assert all(p.startswith("http://opcfoundation.org/UA-Profile/") for p in profiles)
        assert await (await caps.get_child("0:LocaleIdArray")).read_value() == ["en"]
        assert await client.get_node(ua.ObjectIds.Server_Auditing).read_value() is False
        history = client.get_node(ua.ObjectIds.HistoryServerCapabilities)
        assert await (await history.get_child("0:AccessHistoryDataCapability")).read_value()
        aggregates = await (await history.get_child("0:AggregateFunctions")).get_children()
        names = {(await a.read_browse_name()).Name for a in aggregates}
        assert {"Minimum", "Maximum", "Average", "Interpolative"} <= names


@pytest.mark.anyio
async def test_every_sensor_is_an_imu_sensor_type_with_its_series_parts(
        rig: Rig, tmp_path: Path) -> None:
    async with served(rig, tmp_path / "pki") as (client, idx):
        base = client.get_node(ua.ObjectIds.BaseObjectType)
        sensor_type = await base.get_child([f"{idx}:ImuSensorType"])
        assert sensor_type.nodeid == ua.NodeId("ImuSensorType", idx)
        assert await sensor_type.read_node_class() == ua.NodeClass.ObjectType

        async def rule(path: str) -> str:
            node = await sensor_type.get_child([f"{idx}:{p}" for p in path.split("/")])
            (modelling,) = await node.get_referenced_nodes(ua.ObjectIds.HasModellingRule)
            return str((await modelling.read_browse_name()).Name)

        # what every series has is Mandatory; the rest Optional
        assert await rule("Acceleration") == "Mandatory"
        assert await rule("AngularRate") == "Mandatory"
        assert await rule("Status") == "Mandatory"
        for optional in ("Angles", "MagneticField", "Quaternion"):
            assert await rule(optional) == "Optional", optional
        assert await rule("Angles/pitch") == "Mandatory"  # within its group
        sensors = client.get_node(ua.NodeId(f"{GID}.Sensors", idx))
        parts = {}
        for name in ("boom", "mast", "base"):
            node = await sensors.get_child([f"{idx}:{name}"])
            assert (await node.read_type_definition()) == sensor_type.nodeid, name
            parts[name] = {(await c.read_browse_name()).Name for c in await node.get_children()}
        assert {"Angles", "MagneticField", "Quaternion"} <= parts["boom"]  # an AH
        assert "MagneticField" not in parts["mast"] and "Angles" in parts["mast"]  # a VG
        assert not {"Angles", "Quaternion", "MagneticField"} & parts["base"]  # an IMU
        declared = {(await c.read_browse_name()).Name for c in await sensor_type.get_children()}
        for name, have in parts.items():
            assert have <= declared, (name, have - declared)


@pytest.mark.anyio
async def test_every_node_of_the_gateway_has_a_string_id_in_its_namespace(
        rig: Rig, tmp_path: Path) -> None:
    async with served(rig, tmp_path / "pki") as (client, idx):
        roots = [client.get_node(ua.NodeId("ImuSensorType", idx)),
                 client.get_node(ua.NodeId(GID, idx))]
        strays = []
        count = 0
        for root in roots:
            async for node in walk(root):
                if node.nodeid.NamespaceIndex == 0:
                    # namespace 0's own nodes that ours reference (the modelling rules)
                    continue
                count += 1
                if node.nodeid.NamespaceIndex != idx or \
                        node.nodeid.NodeIdType != ua.NodeIdType.String:
                    strays.append(node.nodeid.to_string())
        assert count > 100 and not strays, strays
        pitch = client.get_node(ua.NodeId(f"{GID}.Sensors.boom.Angles.pitch", idx))
        span = await pitch.get_child("0:EURange")
        assert span.nodeid == ua.NodeId(f"{GID}.Sensors.boom.Angles.pitch.EURange", idx)
        assert await span.read_data_type() == ua.NodeId(ua.ObjectIds.Range)
        units = await pitch.get_child("0:EngineeringUnits")
        assert units.nodeid == ua.NodeId(f"{GID}.Sensors.boom.Angles.pitch.EngineeringUnits",
                                         idx)
        assert await units.read_data_type() == ua.NodeId(ua.ObjectIds.EUInformation)
        # nothing of ours was put in namespace 0 (asyncua numbers from 20000 there)
        ours = client.get_node(ua.NodeId(20001, 0))
        with pytest.raises(ua.UaStatusCodeError):
            await ours.read_browse_name()


async def _call(client: Client, obj: ua.NodeId, method: ua.NodeId,
                *args: ua.Variant) -> ua.CallMethodResult:
    (result,) = await client.uaclient.call([ua.CallMethodRequest(
        ObjectId=obj, MethodId=method, InputArguments=list(args))])
    return result


@pytest.mark.anyio
async def test_a_call_of_the_wrong_shape_is_refused_and_the_sensor_hears_nothing(
        rig: Rig, tmp_path: Path) -> None:
    """Part 4 5.11.2: too many arguments, too few, one of the wrong type, a method of
    another object; then the right calls, on the sensor's method and on its type's."""
    port = free_port()
    cfg = rig.config(port, tmp_path / "pki", anonymous=False, allow_commands=True,
                     users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        client = Client(f"opc.tcp://127.0.0.1:{port}/")
        client.set_user("operator")
        client.set_password(PASSWORD)
        async with client:
            idx = await client.get_namespace_index(NS)

            def nid(path: str) -> ua.NodeId:
                return ua.NodeId(f"{GID}.Sensors.{path}", idx)

            double, text = ua.VariantType.Double, ua.VariantType.String
            codes = ua.StatusCodes
            heard = sum(rig.ah.writes_heard.values())
            too_many = await _call(client, nid("boom"), nid("boom.read_settings"),
                                   ua.Variant(1, ua.VariantType.Int32))
            assert too_many.StatusCode.value == codes.BadTooManyArguments
            missing = await _call(client, nid("boom"), nid("boom.set_declination"))
            assert missing.StatusCode.value == codes.BadArgumentsMissing
            wrong = await _call(client, nid("boom"), nid("boom.set_declination"),
                                ua.Variant("east", text))
            assert wrong.StatusCode.value == codes.BadInvalidArgument
            assert [r.value for r in wrong.InputArgumentResults] == [codes.BadTypeMismatch]
            elsewhere = await _call(client, nid("mast"), nid("boom.set_declination"),
                                    ua.Variant(2.5, double))
            assert elsewhere.StatusCode.value == codes.BadMethodInvalid
            assert sum(rig.ah.writes_heard.values()) == heard
            assert rig.ah.settings.declination == 0.0
            # a Float where a Double is declared is a number all the same
            done = await _call(client, nid("boom"), nid("boom.set_declination"),
                               ua.Variant(2.5, ua.VariantType.Float))
            assert done.StatusCode.is_good(), done.StatusCode
            assert rig.ah.settings.declination == pytest.approx(2.5)
            # the type's declaration, called on an instance, runs that sensor's method
            declared = ua.NodeId("ImuSensorType.set_zero_type", idx)
            typed = await _call(client, nid("mast"), declared, ua.Variant("relative", text))
            assert typed.StatusCode.is_good(), typed.StatusCode
            assert rig.vg.settings.zero_type == "relative"
            # … but not one the sensor's series does not have (a VG has no declination)
            absent = await _call(client, nid("mast"), ua.NodeId(
                "ImuSensorType.set_declination", idx), ua.Variant(1.0, double))
            assert absent.StatusCode.value == codes.BadMethodInvalid
