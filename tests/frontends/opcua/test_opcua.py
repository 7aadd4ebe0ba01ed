"""The OPC UA server (docs/opcua.md) against asyncua's own client, here, and Node's
node-opcua (tests/frontends/opcua/test_opcua_node.py).  Expected values come from the simulator;
node ids and units are written out from docs/opcua.md, not taken from the server."""

from __future__ import annotations

import asyncio
import math
import socket
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from support.derived import EXACT, exact_tilt
from support.harness import expected, free_port, running, tolerance, until

from imu_gateway.errors import StartupError
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, SimSensor, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "ua-test"
NS = "urn:imu-gateway"
READING = Motion.from_seed(11).sample(4.0)
DEGREE = (ord("D") << 8) | ord("D")  # UNECE "DD", as OPC UA packs it


def _config(port: int, pki: Path, native: str, modbus: str, **opcua: Any) -> dict[str, Any]:
    def line(name: str, path: str, protocol: str, sensor: dict[str, Any]) -> dict[str, Any]:
        return {"name": name, "port": path, "baudrate": 115200, "protocol": protocol,
                "timeout_ms": 300, "sensors": [sensor]}

    return {"gateway_id": GID,
            "buses": [line("a", native, "native", {"name": "boom", "series": "AH",
                                                   "poll_hz": 20, "stale_after_ms": 400}),
                      line("b", modbus, "modbus", {"name": "mast", "series": "VG",
                                                   "address": 1, "poll_hz": 20})],
            "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": str(pki), **opcua}}


class Lines:
    def __init__(self, ah: SimSensor, vg: SimSensor, native: str, modbus: str,
                 faults: Faults) -> None:
        self.ah, self.vg, self.native, self.modbus, self.faults = ah, vg, native, modbus, faults


@pytest.fixture
def lines() -> Iterator[Lines]:
    faults = Faults()
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING),
                     faults=faults)
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=115200, source=hold(READING))
    with simulated([ah]) as a, simulated([vg]) as b:
        yield Lines(ah, vg, a.path, b.path, faults)


def node(client: Client, idx: int, path: str) -> Any:
    return client.get_node(ua.NodeId(f"{GID}.{path}", idx))


@pytest.mark.anyio
async def test_an_ipv6_listen_address_serves(tmp_path: Path, lines: Lines) -> None:
    """``listen: "[::1]:port"``: the endpoint URL carries the host in brackets (it
    once did not, and asyncua's URL parse ended the start)."""
    if not socket.has_ipv6:
        pytest.skip("this machine has no IPv6")
    port = free_port()
    cfg = _config(port, tmp_path / "pki", lines.native, lines.modbus, allow_none=True)
    cfg["opcua"]["listen"] = f"[::1]:{port}"
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with Client(f"opc.tcp://[::1]:{port}/") as client:
            idx = await client.get_namespace_index(NS)
            assert await node(client, idx, "Sensors.boom.Series").read_value() == "AH"


@pytest.mark.anyio
async def test_a_pki_dir_that_cannot_be_used_is_named_at_start(tmp_path: Path,
                                                                 lines: Lines) -> None:
    """Not the port: the certificate's folder is named, with what it is for."""
    (tmp_path / "a-file").write_text("")
    cfg = _config(free_port(), tmp_path / "a-file" / "pki", lines.native, lines.modbus,
                  allow_none=True)
    with pytest.raises(StartupError, match=r"opcua.pki_dir .*a-file/pki: .*certificate"):
        async with running(cfg):
            pass


@pytest.mark.anyio
async def test_browse_read_and_units(tmp_path: Path, lines: Lines) -> None:
    port = free_port()
    cfg = _config(port, tmp_path / "pki", lines.native, lines.modbus, allow_none=True)
    async with running(cfg) as gw:
        await until(lambda: all(gw.cache.snapshot(n).seq >= 2 for n in ("boom", "mast")))
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index(NS)
            top = await client.nodes.objects.get_child([f"{idx}:IMU Gateway", f"{idx}:{GID}"])
            sensors = await top.get_child([f"{idx}:Sensors"])
            names = {(await n.read_browse_name()).Name for n in await sensors.get_children()}
            assert names == {"boom", "mast"}
            boom = await sensors.get_child([f"{idx}:boom"])
            groups = {(await n.read_browse_name()).Name for n in await boom.get_children()}
            assert {"Angles", "Acceleration", "AngularRate", "MagneticField", "Quaternion",
                    "Status", "Sequence", "Errors", "Series", "Protocol", "Address"} <= groups
            assert "Age" not in groups  # (it froze when the sensor stopped)
            mast = await sensors.get_child([f"{idx}:mast"])
            vg_groups = {(await n.read_browse_name()).Name for n in await mast.get_children()}
            assert "MagneticField" not in vg_groups  # a VG measures none
            buses = await top.get_child([f"{idx}:Buses"])
            assert len(await buses.get_children()) == 2
            # values: the simulator's, as AnalogItemType with units and range
            for sensor, sim, protocol, groups_of in (
                    ("boom", lines.ah, WireProtocol.NATIVE, "AH"),
                    ("mast", lines.vg, WireProtocol.MODBUS, "VG")):
                for name, value in expected(sim).items():
                    folder = _FOLDER[name]
                    item = node(client, idx, f"Sensors.{sensor}.{folder}.{name}")
                    dv = await item.read_data_value()
                    assert dv.StatusCode.is_good(), (sensor, name, dv.StatusCode)
                    slack = tolerance(protocol, name, value) + 1e-6 * max(1, abs(value))
                    assert abs(dv.Value.Value - value) <= slack, (sensor, name, dv.Value.Value)
                assert await node(client, idx, f"Sensors.{sensor}.Series").read_value() \
                    == groups_of
            pitch = node(client, idx, "Sensors.boom.Angles.pitch")
            assert (await pitch.read_type_definition()).Identifier == ua.ObjectIds.AnalogItemType
            units = await (await pitch.get_child(["0:EngineeringUnits"])).read_value()
            assert units.UnitId == DEGREE and units.NamespaceUri.endswith("un/cefact")
            span = await (await pitch.get_child(["0:EURange"])).read_value()
            assert (span.Low, span.High) == (-999.99, 999.99)
            await until(lambda: gw.stats()[0].transactions > 0)
            transactions = node(client, idx, "Buses.a.Transactions")
            await until(_is_positive(transactions), 5)


@pytest.mark.anyio
async def test_values_are_doubles_as_the_sensor_gave_them_with_the_derived(
        tmp_path: Path) -> None:
    """A native sensor's 32.52 reads 32.52 (Double), not the 32.52000045776367 of a
    Float; the Tilt and Vibration folders carry the derived values, with their units."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(EXACT))
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=115200, source=hold(EXACT))
    port = free_port()
    with simulated([ah]) as a, simulated([vg]) as b:
        cfg = _config(port, tmp_path / "pki", a.path, b.path, allow_none=True)
        async with running(cfg) as gw, Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            await until(lambda: gw.cache.snapshot("boom").seq >= 1)
            idx = await client.get_namespace_index(NS)
            pitch = node(client, idx, "Sensors.boom.Angles.pitch")
            assert await pitch.read_data_type() == ua.NodeId(ua.ObjectIds.Double)
            value = (await pitch.read_data_value()).Value
            assert (value.Value, value.VariantType) == (32.52, ua.VariantType.Double)
            want_tilt, want_direction = exact_tilt()
            for sensor in ("boom", "mast"):
                tilt = node(client, idx, f"Sensors.{sensor}.Tilt.tilt")
                direction = node(client, idx, f"Sensors.{sensor}.Tilt.tilt_direction")
                assert await tilt.read_data_type() == ua.NodeId(ua.ObjectIds.Double)
                got = (await tilt.read_value(), await direction.read_value())
                # the Modbus VG's pitch is a float32: its tilt may differ in the last digit
                assert got == pytest.approx((want_tilt, want_direction), abs=0.011), sensor
                shake = node(client, idx, f"Sensors.{sensor}.Vibration.vibration")
                await until(_reads(shake, 0.0))  # still, at 20 Hz: 0 once a second is in
            units = await (await tilt.get_child(["0:EngineeringUnits"])).read_value()
            assert units.UnitId == DEGREE
            units = await (await shake.get_child(["0:EngineeringUnits"])).read_value()
            assert units.UnitId == int.from_bytes(b"K40", "big")


@pytest.mark.anyio
async def test_every_sample_node_holds_the_variant_type_of_its_data_type(
        tmp_path: Path, lines: Lines) -> None:
    """The gateway writes its samples past asyncua's type check (``writes.py``): each
    value and status node of each sensor, as a client reads it, holds a Variant of
    the type its DataType says."""
    port = free_port()
    cfg = _config(port, tmp_path / "pki", lines.native, lines.modbus, allow_none=True)
    async with running(cfg) as gw, Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        await until(lambda: all(gw.cache.snapshot(s).seq >= 2 for s in ("boom", "mast")))
        assert gw.opcua is not None
        written = [nodeid for sensor in ("boom", "mast")
                   for nodeid in [n for _, n in gw.opcua.nodes.values[sensor]] +
                   [n for _, n in gw.opcua.nodes.status[sensor]]]
        assert len(written) > 30
        for nodeid in written:
            ua_node = client.get_node(nodeid)
            dtype = await ua_node.read_data_type()
            value = (await ua_node.read_data_value()).Value
            assert dtype.NamespaceIndex == 0 and isinstance(dtype.Identifier, int)
            assert value.VariantType == ua.VariantType(dtype.Identifier), nodeid


def _reads(item: Any, want: float) -> Any:
    async def check() -> bool:
        return bool(await item.read_value() == want)
    return check


def _is_positive(item: Any) -> Any:
    async def check() -> bool:
        return bool(await item.read_value() > 0)
    return check


_FOLDER = {**dict.fromkeys(("pitch", "roll", "yaw"), "Angles"),
           **{f"accel_{a}": "Acceleration" for a in "xyz"},
           **{f"gyro_{a}": "AngularRate" for a in "xyz"},
           **{f"mag_{a}": "MagneticField" for a in "xyz"},
           **{f"q{i}": "Quaternion" for i in range(4)}}


class _Changes:
    def __init__(self) -> None:
        self.values: dict[str, list[Any]] = {}

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        key = str(node.nodeid.Identifier).rsplit(".", 1)[-1]
        self.values.setdefault(key, []).append(data.monitored_item.Value)

    def of(self, key: str) -> list[Any]:
        return self.values.get(key, [])


@pytest.mark.anyio
async def test_a_subscription_gets_each_sample_and_the_quality_change(
        tmp_path: Path, lines: Lines) -> None:
    port = free_port()
    cfg = _config(port, tmp_path / "pki", lines.native, lines.modbus, allow_none=True)
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 2)
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index(NS)
            changes = _Changes()
            subscription = await client.create_subscription(50, changes)
            # the held reading's values do not change; each sample's Sequence does
            await subscription.subscribe_data_change(
                [node(client, idx, "Sensors.boom.Sequence"),
                 node(client, idx, "Sensors.boom.Angles.pitch")])
            await until(lambda: len(changes.of("Sequence")) >= 5)
            samples = changes.of("Sequence")
            stamps: list[datetime] = [v.SourceTimestamp for v in samples]
            assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
            numbers = [v.Value.Value for v in samples]
            assert numbers == sorted(numbers) and len(set(numbers)) == len(numbers)
            assert changes.of("pitch")[0].StatusCode.is_good()
            lines.faults.stalled = True  # stale, then offline

            def saw(code: int) -> bool:
                return any(v.StatusCode.value == code for v in changes.of("pitch"))

            await until(lambda: saw(ua.StatusCodes.UncertainLastUsableValue), 10)
            await until(lambda: saw(ua.StatusCodes.BadCommunicationError), 30)
            lines.faults.stalled = False
            await until(lambda: changes.of("pitch")[-1].StatusCode.is_good(), 30)
            await subscription.delete()


@pytest.mark.anyio
async def test_never_read_is_bad_no_communication(tmp_path: Path, lines: Lines) -> None:
    lines.faults.stalled = True
    port = free_port()
    cfg = _config(port, tmp_path / "pki", lines.native, lines.modbus, allow_none=True)
    async with running(cfg), Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        idx = await client.get_namespace_index(NS)
        dv = await node(client, idx, "Sensors.boom.Angles.pitch").read_data_value(
            raise_on_bad_status=False)
        assert dv.StatusCode.value == ua.StatusCodes.BadNoCommunication
        assert dv.Value.Value is None or math.isnan(dv.Value.Value)  # no value to show


async def _client_cert(folder: Path, name: str) -> tuple[Path, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    key, cert = folder / f"{name}.pem", folder / f"{name}.der"
    await setup_self_signed_certificate(
        key, cert, f"urn:test:{name}", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": name})
    return cert, key


@pytest.mark.anyio
async def test_security_users_and_a_method_that_reaches_the_sensor(
        tmp_path: Path, lines: Lines) -> None:
    port = free_port()
    pki = tmp_path / "pki"
    cert, key = await _client_cert(tmp_path / "client", "scada")
    (pki / "trusted").mkdir(parents=True)
    (pki / "trusted" / "scada.der").write_bytes(cert.read_bytes())
    stranger, stranger_key = await _client_cert(tmp_path / "client", "stranger")
    cfg = _config(port, pki, lines.native, lines.modbus, anonymous=False,
                  allow_commands=True, users={"operator": "${UA_PASSWORD}"})
    url = f"opc.tcp://127.0.0.1:{port}/"
    async with running(cfg, env={"UA_PASSWORD": "s3cret"}) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        # the server's private key is its owner's alone
        assert (pki / "server_key.pem").stat().st_mode & 0o777 == 0o600

        async def connect(user: str | None, password: str | None,
                          certificate: Path = cert, private_key: Path = key) -> Client:
            client = Client(url)
            await client.set_security(SecurityPolicyBasic256Sha256, str(certificate),
                                      str(private_key), mode=ua.MessageSecurityMode.SignAndEncrypt,
                                      server_certificate=str(pki / "server_cert.der"))
            client.application_uri = f"urn:test:{certificate.stem}"
            if user is not None:
                client.set_user(user)
                client.set_password(password or "")
            await client.connect()
            return client

        # no security mode None offered
        with pytest.raises(Exception):  # noqa: B017 - asyncua raises several kinds here
            async with Client(url) as plain:
                await plain.get_namespace_index(NS)
        for user, password in ((None, None), ("operator", "wrong"), ("nobody", "s3cret")):
            with pytest.raises(ua.UaError):
                await connect(user, password)
        with pytest.raises(Exception):  # noqa: B017 - an untrusted client certificate
            await connect("operator", "s3cret", stranger, stranger_key)
        client = await connect("operator", "s3cret")
        try:
            idx = await client.get_namespace_index(NS)
            boom = node(client, idx, "Sensors.boom")
            method = node(client, idx, "Sensors.boom.set_zero_type")
            result = await boom.call_method(method, ua.Variant("relative", ua.VariantType.String))
            assert result.startswith("set_zero_type: ok")
            assert lines.ah.settings.zero_type == "relative"
            bad = ua.Variant("sideways", ua.VariantType.String)
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await boom.call_method(method, bad)
            assert refused.value.code == ua.StatusCodes.BadInvalidArgument
            assert lines.ah.settings.zero_type == "relative"
        finally:
            await client.disconnect()
    await asyncio.sleep(0)


@pytest.mark.anyio
async def test_sign_only_is_offered_too(tmp_path: Path, lines: Lines) -> None:
    """Basic256Sha256 Sign (integrity without encryption) as well as SignAndEncrypt."""
    port = free_port()
    pki = tmp_path / "pki"
    cert, key = await _client_cert(tmp_path / "client", "historian")
    (pki / "trusted").mkdir(parents=True)
    (pki / "trusted" / "historian.der").write_bytes(cert.read_bytes())
    async with running(_config(port, pki, lines.native, lines.modbus)) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        client = Client(f"opc.tcp://127.0.0.1:{port}/")
        await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                                  mode=ua.MessageSecurityMode.Sign,
                                  server_certificate=str(pki / "server_cert.der"))
        client.application_uri = "urn:test:historian"
        await client.connect()
        try:
            idx = await client.get_namespace_index(NS)
            status = await node(client, idx, "Sensors.boom.Status").read_value()
            assert status == "ok"
            modes = {e.SecurityMode for e in await client.get_endpoints()}
            assert modes == {ua.MessageSecurityMode.Sign, ua.MessageSecurityMode.SignAndEncrypt}
        finally:
            await client.disconnect()
