"""Alarms as OPC UA Part 9 conditions (docs/opcua.md, "Alarms and conditions"), against
the running gateway on a simulated sensor that leans past the limit: asyncua's client
subscribes to events on the sensor object and on the Server object, receives the
transition with its severity, after the on-delay, and acknowledges it; a session
without the rights is refused, and the value comes back through the hysteresis.

Waits are for events (the subscription's, the cache's sequence numbers), never for a
fixed time."""

from __future__ import annotations

import asyncio
import json
import shutil
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID
from support import ROOT
from support.harness import free_port, running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Angles, Reading, Series, WireProtocol
from imu_gateway.simulator import SimSensor, hold, make_sensor, simulated

NODE_DIR = ROOT / "tests" / "node"
GID = "ua-alarms"
NS = "urn:imu-gateway"
ON_DELAY = 0.3
PASSWORD = "s3cret-alarm"
FIELDS = ["EventId", "EventType", "SourceNode", "SourceName", "Time", "Message", "Severity",
          "ConditionName", "Retain", "ActiveState", "ActiveState/Id", "AckedState",
          "AckedState/Id", "Value", "HighLimit", "LowLimit", "ClientUserId", "Comment"]


def leaning(pitch: float) -> Any:
    return hold(Reading(angles=Angles(pitch, 0.0, 0.0)))


def config(port: int, pki: str, **opcua: Any) -> dict[str, Any]:
    alarm = {"name": "boom_lean", "field": "pitch", "above": 5.0, "hysteresis": 0.5,
             "on_delay_s": ON_DELAY, "severity": "warning"}
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": "", "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "alarms": [alarm]}]}],
            "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": pki, "allow_none": True,
                      **opcua}}


@pytest.fixture
def boom() -> Any:
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, baud=115200, source=leaning(1.0))
    with simulated([sim]) as line:
        yield sim, line.path


class Events:
    """An event subscription's notifications, as dicts of the selected fields."""

    def __init__(self) -> None:
        self.seen: list[dict[str, Any]] = []

    def event_notification(self, event: Any) -> None:
        self.seen.append(event.get_event_props_as_fields_dict())

    def of(self, name: str, active: bool, acked: bool) -> dict[str, Any] | None:
        return next((e for e in self.seen if e["ConditionName"].Value == name
                     and e["ActiveState/Id"].Value is active
                     and e["AckedState/Id"].Value is acked), None)

    async def wait_for(self, name: str, active: bool, acked: bool) -> dict[str, Any]:
        await until(lambda: self.of(name, active, acked) is not None)
        found = self.of(name, active, acked)
        assert found is not None
        return found


def event_filter() -> ua.EventFilter:
    """Select clauses by browse path on ExclusiveLimitAlarmType (ConditionId too)."""
    clauses = []
    for name in FIELDS:
        op = ua.SimpleAttributeOperand()
        op.TypeDefinitionId = ua.NodeId(ua.ObjectIds.ExclusiveLimitAlarmType)
        op.BrowsePath = [ua.QualifiedName(part, 0) for part in name.split("/")]
        op.AttributeId = ua.AttributeIds.Value
        clauses.append(op)
    condition_id = ua.SimpleAttributeOperand()
    condition_id.TypeDefinitionId = ua.NodeId(ua.ObjectIds.ConditionType)
    condition_id.AttributeId = ua.AttributeIds.NodeId
    clauses.append(condition_id)
    return ua.EventFilter(SelectClauses=clauses)


@pytest.fixture
async def pki(tmp_path: Any) -> AsyncIterator[str]:
    yield str(tmp_path / "pki")


async def subscribe(client: Client, node: Node) -> tuple[Events, Any]:
    events = Events()
    sub = await client.create_subscription(50, events)
    await sub._subscribe(node, ua.AttributeIds.EventNotifier, event_filter())
    return events, sub


async def readings_pass(gateway: Gateway, n: int = 3) -> None:
    seq = gateway.cache.snapshot("boom").seq
    await until(lambda: gateway.cache.snapshot("boom").seq >= seq + n)


async def acknowledge(client: Client, condition: ua.NodeId, event_id: bytes,
                      comment: str = "seen") -> None:
    await client.get_node(condition).call_method(
        ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
        ua.Variant(event_id, ua.VariantType.ByteString),
        ua.Variant(ua.LocalizedText(comment, "en"), ua.VariantType.LocalizedText))


@pytest.mark.anyio
async def test_a_lean_is_an_event_on_the_sensor_and_an_operator_acknowledges_it(
        boom: tuple[SimSensor, str], pki: str) -> None:
    sim, path = boom
    port = free_port()
    cfg = config(port, pki, anonymous=False, allow_commands=True,
                 users={"operator": PASSWORD})
    cfg["buses"][0]["port"] = path
    url = f"opc.tcp://127.0.0.1:{port}/"
    async with running(cfg) as gateway:
        await readings_pass(gateway)
        client = Client(url)
        client.set_user("operator")
        client.set_password(PASSWORD)
        async with client:
            idx = await client.get_namespace_index(NS)
            sensor = client.get_node(ua.NodeId(f"{GID}.Sensors.boom", idx))
            condition = ua.NodeId(f"{GID}.Sensors.boom.Alarms.boom_lean", idx)
            # the notifiers: the sensor and the gateway object, under the Server
            for notifier in (sensor, client.get_node(ua.NodeId(GID, idx))):
                assert ua.EventNotifier.SubscribeToEvents in \
                    await notifier.read_event_notifier()
            conditions = await sensor.get_referenced_nodes(ua.ObjectIds.HasCondition)
            assert {c.nodeid for c in conditions} == {
                condition, ua.NodeId(f"{GID}.Sensors.boom.Alarms.communication", idx)}
            node = client.get_node(condition)
            assert (await node.read_type_definition()) == \
                ua.NodeId(ua.ObjectIds.ExclusiveLimitAlarmType)
            high = await node.get_child([ua.QualifiedName("HighLimit", 0)])
            assert await high.read_value() == 5.0

            on_sensor, _ = await subscribe(client, sensor)
            on_server, _ = await subscribe(client, client.nodes.server)

            leaned_at = time.time()
            sim.source = leaning(10.0)
            raised = await on_sensor.wait_for("boom_lean", active=True, acked=False)
            assert raised["Severity"].Value == 500
            assert raised["SourceName"].Value == "boom"
            assert raised["SourceNode"].Value == sensor.nodeid
            assert raised["NodeId"].Value == condition
            assert raised["EventType"].Value == ua.NodeId(ua.ObjectIds.ExclusiveLimitAlarmType)
            assert raised["Value"].Value == 10.0 and raised["HighLimit"].Value == 5.0
            assert raised["LowLimit"].Value is None
            assert raised["Retain"].Value is True
            assert raised["ActiveState"].Value.Text == "Active"
            assert raised["AckedState"].Value.Text == "Unacknowledged"
            assert "boom/boom_lean active_unacked: pitch 10" in raised["Message"].Value.Text
            # the on-delay: not raised before the lean had held for it
            assert raised["Time"].Value.timestamp() >= leaned_at + ON_DELAY - 0.002
            same = await on_server.wait_for("boom_lean", active=True, acked=False)
            assert same["EventId"].Value == raised["EventId"].Value

            # Part 9's refusals: an EventId it never sent, a node that is no condition
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await acknowledge(client, condition, b"not an event id")
            assert refused.value.code == ua.StatusCodes.BadEventIdUnknown
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await acknowledge(client, sensor.nodeid, raised["EventId"].Value)
            assert refused.value.code == ua.StatusCodes.BadNodeIdUnknown

            await acknowledge(client, condition, raised["EventId"].Value, "on my way")
            acked = await on_sensor.wait_for("boom_lean", active=True, acked=True)
            assert acked["ClientUserId"].Value == "operator (opcua 127.0.0.1)"
            assert acked["Comment"].Value.Text == "on my way"
            assert acked["Retain"].Value is True
            journal = gateway.alarm_journal()
            assert journal[-1].by == "operator (opcua 127.0.0.1)"
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await acknowledge(client, condition, acked["EventId"].Value)
            assert refused.value.code == ua.StatusCodes.BadConditionBranchAlreadyAcked

            # back, but not through the hysteresis (4.7 > 4.5): no event
            sim.source = leaning(4.7)
            await until(lambda: gateway.cache.snapshot("boom").reading is not None and
                        gateway.cache.snapshot("boom").reading.angles.pitch == 4.7)  # type: ignore[union-attr]
            await readings_pass(gateway)
            assert on_sensor.of("boom_lean", active=False, acked=True) is None
            sim.source = leaning(4.0)
            cleared = await on_sensor.wait_for("boom_lean", active=False, acked=True)
            assert cleared["Retain"].Value is False and cleared["Value"].Value == 4.0
            names = [e["ConditionName"].Value for e in on_sensor.seen]
            assert names == ["boom_lean"] * 3, names  # one event a transition, no more


@pytest.mark.anyio
async def test_without_the_rights_no_acknowledge_and_a_refresh_tells_what_is_on(
        boom: tuple[SimSensor, str], pki: str) -> None:
    """Anonymous sessions (commands off): they see the events, cannot acknowledge, and
    ConditionRefresh gives a new subscriber the retained conditions."""
    sim, path = boom
    port = free_port()
    cfg = config(port, pki)
    cfg["buses"][0]["port"] = path
    async with running(cfg) as gateway:
        await readings_pass(gateway)
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index(NS)
            sensor = client.get_node(ua.NodeId(f"{GID}.Sensors.boom", idx))
            condition = ua.NodeId(f"{GID}.Sensors.boom.Alarms.boom_lean", idx)
            first, _ = await subscribe(client, sensor)
            sim.source = leaning(10.0)
            raised = await first.wait_for("boom_lean", active=True, acked=False)
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await acknowledge(client, condition, raised["EventId"].Value)
            assert refused.value.code == ua.StatusCodes.BadUserAccessDenied
            await readings_pass(gateway)
            assert gateway.alarm_states()[0].state.value == "active_unacked"

            later, sub = await subscribe(client, client.nodes.server)
            await client.nodes.server.call_method(
                ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
                ua.Variant(sub.subscription_id, ua.VariantType.UInt32))
            again = await later.wait_for("boom_lean", active=True, acked=False)
            assert again["EventId"].Value == raised["EventId"].Value
            # another session cannot refresh (and so flood) this one's subscription
            async with Client(f"opc.tcp://127.0.0.1:{port}/") as other:
                with pytest.raises(ua.UaStatusCodeError) as refused:
                    await other.nodes.server.call_method(
                        ua.NodeId(ua.ObjectIds.ConditionType_ConditionRefresh),
                        ua.Variant(sub.subscription_id, ua.VariantType.UInt32))
                assert refused.value.code == ua.StatusCodes.BadSubscriptionIdInvalid
            await asyncio.sleep(0)


async def trusted_client(folder: Path, pki: Path) -> tuple[Path, Path]:
    """A client certificate (PEM) and key, put in the server's trust list."""
    folder.mkdir(parents=True)
    key, der = folder / "key.pem", folder / "cert.der"
    await setup_self_signed_certificate(
        key, der, "urn:test:node-opcua", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": "node-opcua alarm client"})
    pem = folder / "cert.pem"
    pem.write_bytes(x509.load_der_x509_certificate(der.read_bytes()).public_bytes(
        serialization.Encoding.PEM))
    (pki / "trusted").mkdir(parents=True, exist_ok=True)
    (pki / "trusted" / "node-opcua.der").write_bytes(der.read_bytes())
    return pem, key


@pytest.mark.anyio
async def test_node_opcua_receives_the_transition_and_acknowledges_it(
        boom: tuple[SimSensor, str], tmp_path: Path) -> None:
    """node-opcua (tests/node/opcua_alarm.js) subscribes to the sensor's events, gets
    the raise with its severity, acknowledges it with session.acknowledgeCondition, and
    gets the acknowledged event."""
    sim, path = boom
    node = shutil.which("node")
    assert node is not None, "node is needed: scripts/bootstrap --test installs it"
    port, pki = free_port(), tmp_path / "pki"
    cert, key = await trusted_client(tmp_path / "client", pki)
    cfg = config(port, str(pki), anonymous=False, allow_commands=True,
                 users={"operator": PASSWORD})
    cfg["buses"][0]["port"] = path
    async with running(cfg) as gateway:
        await readings_pass(gateway)
        proc = await asyncio.create_subprocess_exec(
            node, str(NODE_DIR / "opcua_alarm.js"), f"opc.tcp://127.0.0.1:{port}/", GID,
            "boom", "boom_lean", "operator", PASSWORD,
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={"NODE_PATH": str(NODE_DIR / "node_modules"), "UA_CERT": str(cert),
                 "UA_KEY": str(key), "HOME": str(cert.parent)})
        assert proc.stdout is not None
        try:
            lines: list[str] = []
            while not lines or lines[-1] != "SUBSCRIBED":
                line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
                assert line, (lines, (await proc.stderr.read()).decode()[-2000:])  # type: ignore[union-attr]
                lines.append(line.strip())
            sim.source = leaning(10.0)
            out, err = await asyncio.wait_for(proc.communicate(), 60)
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        assert proc.returncode == 0, err.decode()[-2000:]
        (result,) = [x for x in out.decode().splitlines() if x.startswith("RESULT ")]
        got = json.loads(result.removeprefix("RESULT "))
        assert gateway.alarm_journal()[-1].by == "operator (opcua 127.0.0.1)"
    raised, acked = got["events"][0], got["events"][-1]
    ns = got["ns"]
    assert raised["Severity"] == 500 and raised["SourceName"] == "boom"
    assert raised["SourceNode"] == f"ns={ns};s={GID}.Sensors.boom"
    assert raised["ConditionId"] == f"ns={ns};s={GID}.Sensors.boom.Alarms.boom_lean"
    assert raised["EventType"] == "ns=0;i=9341"  # ExclusiveLimitAlarmType
    assert (raised["ActiveState"], raised["AckedState"]) == ("Active", "Unacknowledged")
    assert raised["HighLimit"] == 5.0 and raised["Retain"] is True
    assert got["ack"] == "Good"
    assert (acked["AckedState"], acked["AckedState.Id"]) == ("Acknowledged", True)
    assert acked["ClientUserId"] == "operator (opcua 127.0.0.1)"
    assert acked["EventId"] != raised["EventId"]
