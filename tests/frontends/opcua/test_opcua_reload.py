"""A reload that changes the sensors, seen by an OPC UA client that stays connected
(docs/opcua.md, "A reload"): asyncua's own client, written from OPC UA Parts 3 and 4
(node ids from docs/opcua.md, not taken from the server)."""

from __future__ import annotations

import copy
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.ua import uaerrors
from support.harness import free_port, running, until

from imu_gateway.config import config_from_dict
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "ua-reload"
NS = "urn:imu-gateway"
NODE_ADDED, NODE_DELETED = 1, 2  # ModelChangeStructureDataType's Verb bits (Part 5)


def _line(name: str, path: str, sensors: list[dict[str, Any]]) -> dict[str, Any]:
    return {"name": name, "port": path, "baudrate": 115200, "protocol": "native",
            "timeout_ms": 300, "sensors": sensors}


@pytest.fixture
def paths() -> Iterator[tuple[str, str]]:
    """Line a: boom (moving, so its pitch changes every sample).  Line b: arm at
    address 1 and jib at 2, held still."""
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    still = hold(Motion.from_seed(5).sample(2.0))
    arm = make_sensor(WireProtocol.NATIVE, Series.AH, 1, baud=115200, source=still)
    jib = make_sensor(WireProtocol.NATIVE, Series.VG, 2, baud=115200, source=still)
    with simulated([boom]) as a, simulated([arm, jib]) as b:
        yield a.path, b.path


def _config(port: int, pki: Path, a: str, b: str) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [_line("a", a, [{"name": "boom", "series": "AH", "poll_hz": 20}]),
                      _line("b", b, [{"name": "arm", "series": "AH", "address": 1,
                                      "poll_hz": 20}])],
            "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": str(pki), "allow_none": True}}


def _arm_out_jib_in(config: dict[str, Any]) -> dict[str, Any]:
    new = copy.deepcopy(config)
    new["buses"][1]["sensors"] = [{"name": "jib", "series": "VG", "address": 2, "poll_hz": 20}]
    return new


class _Seen:
    """What the subscription delivered: data changes by node id, and events."""

    def __init__(self) -> None:
        self.values: dict[str, list[ua.DataValue]] = {}
        self.events: list[Any] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.values.setdefault(str(node.nodeid.Identifier), []).append(
            data.monitored_item.Value)

    def event_notification(self, event: Any) -> None:
        self.events.append(event)

    def of(self, path: str) -> list[ua.DataValue]:
        return self.values.get(f"{GID}.Sensors.{path}", [])


@pytest.mark.anyio
async def test_a_reload_adds_and_removes_sensors_in_the_same_session(
        tmp_path: Path, paths: tuple[str, str]) -> None:
    """One session across a reload that removes arm and adds jib: the session and its
    subscription go on (boom's pitch keeps coming, same subscription id); jib is
    browseable and readable at once; arm's nodes read BadNodeIdUnknown, and the item
    monitoring arm's pitch is told BadNodeIdUnknown; a GeneralModelChangeEvent from the
    Server object names jib added and arm deleted."""
    port = free_port()
    first = _config(port, tmp_path / "pki", *paths)
    async with running(first) as gw:
        await until(lambda: all(gw.cache.snapshot(n).seq >= 2 for n in ("boom", "arm")))
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index(NS)

            def node(path: str) -> Any:
                return client.get_node(ua.NodeId(f"{GID}.Sensors.{path}", idx))

            seen = _Seen()
            subscription = await client.create_subscription(50, seen)
            sub_id = subscription.subscription_id
            await subscription.subscribe_data_change([node("boom.Angles.pitch"),
                                                      node("arm.Angles.pitch")],
                                                     sampling_interval=0)  # (every value)
            await subscription.subscribe_events(
                client.nodes.server, ua.NodeId(ua.ObjectIds.GeneralModelChangeEventType))
            await until(lambda: len(seen.of("boom.Angles.pitch")) >= 3
                        and len(seen.of("arm.Angles.pitch")) >= 1)
            # (the server's token for this session: a new session would have another;
            # asyncua's client reconnects only when asked to, and is not)
            token = client.uaclient.session.authentication_token

            await gw.reloader._apply(config_from_dict(_arm_out_jib_in(first), env={}))

            # boom's pitch keeps coming on the same subscription
            count = len(seen.of("boom.Angles.pitch"))
            await until(lambda: len(seen.of("boom.Angles.pitch")) >= count + 5)
            assert subscription.subscription_id == sub_id
            assert all(v.StatusCode.is_good() for v in seen.of("boom.Angles.pitch")[count:])
            # the item on arm's pitch: its node is gone
            await until(lambda: any(v.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown
                                    for v in seen.of("arm.Angles.pitch")))
            # jib: browseable and readable in this session
            sensors = client.get_node(ua.NodeId(f"{GID}.Sensors", idx))
            names = {(await n.read_browse_name()).Name for n in await sensors.get_children()}
            assert names == {"boom", "jib"}
            assert await node("jib.Series").read_value() == "VG"
            assert await node("jib.Address").read_value() == 2
            await until(lambda: gw.cache.snapshot("jib").seq >= 2)

            async def jib_good() -> bool:
                return bool((await node("jib.Angles.pitch").read_data_value())
                            .StatusCode.is_good())

            await until(jib_good)
            # arm: gone
            for path in ("arm", "arm.Angles.pitch", "arm.Series", "arm.Alarms.communication"):
                with pytest.raises(uaerrors.BadNodeIdUnknown):
                    await node(path).read_browse_name()
            with pytest.raises(uaerrors.BadNodeIdUnknown):
                await node("arm.Angles.pitch").read_raw_history(
                    datetime.now(UTC) - timedelta(minutes=1), datetime.now(UTC))
            # the event: from the Server object, jib added, arm deleted
            await until(lambda: len(seen.events) >= 1)
            event = seen.events[0]
            assert event.SourceNode == ua.NodeId(ua.ObjectIds.Server)
            verbs = {str(c.Affected.Identifier): c.Verb for c in event.Changes}
            assert verbs[f"{GID}.Sensors.jib"] & NODE_ADDED
            assert verbs[f"{GID}.Sensors.arm"] & NODE_DELETED
            assert client.uaclient.session.authentication_token == token
            await subscription.delete()


@pytest.mark.anyio
async def test_a_changed_sensor_is_rebuilt_or_written_in_place(
        tmp_path: Path, paths: tuple[str, str]) -> None:
    """An alarm added to arm rebuilds arm's subtree: its new condition is there, the
    item on its old pitch is told BadNodeIdUnknown, and the event names arm deleted
    and added.  Then arm's address alone changed: written into its Address variable,
    whose monitored item hears the new value (the subtree is kept, not rebuilt); boom,
    unchanged, goes on in the same subscription throughout."""
    port = free_port()
    first = _config(port, tmp_path / "pki", *paths)
    async with running(first) as gw:
        await until(lambda: all(gw.cache.snapshot(n).seq >= 2 for n in ("boom", "arm")))
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index(NS)

            def node(path: str) -> Any:
                return client.get_node(ua.NodeId(f"{GID}.Sensors.{path}", idx))

            seen = _Seen()
            subscription = await client.create_subscription(50, seen)
            await subscription.subscribe_data_change([node("boom.Angles.pitch"),
                                                      node("arm.Angles.pitch")],
                                                     sampling_interval=0)  # (every value)
            await subscription.subscribe_events(
                client.nodes.server, ua.NodeId(ua.ObjectIds.GeneralModelChangeEventType))
            await until(lambda: len(seen.of("arm.Angles.pitch")) >= 1)
            alarmed = copy.deepcopy(first)
            alarmed["buses"][1]["sensors"][0]["alarms"] = [
                {"name": "arm_lean", "field": "pitch", "above": 80}]
            await gw.reloader._apply(config_from_dict(alarmed, env={}))

            conditions = await node("arm.Alarms").get_children()
            assert {(await c.read_browse_name()).Name for c in conditions} \
                == {"arm_lean", "communication"}
            await until(lambda: any(v.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown
                                    for v in seen.of("arm.Angles.pitch")))
            await until(lambda: len(seen.events) >= 1)
            # the item on the old pitch stays (its client deletes it), but takes no
            # value: the rebuilt arm's samples are not written one by one for it
            assert gw.opcua is not None and gw.opcua.server is not None
            every = gw.opcua.server.watch.every.nodes()
            assert node("boom.Angles.pitch").nodeid in every
            assert node("arm.Angles.pitch").nodeid not in every
            seq = gw.cache.snapshot("arm").seq
            await until(lambda: gw.cache.snapshot("arm").seq >= seq + 2)
            gw.cache.catch_up()
            each = gw.opcua._samples._each  # (the sensors written sample by sample)
            assert "boom" in each and "arm" not in each
            verbs = [(str(c.Affected.Identifier), c.Verb) for c in seen.events[0].Changes]
            assert (f"{GID}.Sensors.arm", NODE_DELETED) in verbs
            assert (f"{GID}.Sensors.arm", NODE_ADDED) in verbs
            assert await node("arm.Address").read_value() == 1

            await subscription.subscribe_data_change([node("arm.Address")])
            await until(lambda: len(seen.of("arm.Address")) >= 1)
            moved = copy.deepcopy(alarmed)
            moved["buses"][1]["sensors"][0]["address"] = 3
            count = len(seen.of("boom.Angles.pitch"))
            await gw.reloader._apply(config_from_dict(moved, env={}))
            await until(lambda: any(v.Value.Value == 3 for v in seen.of("arm.Address")))
            assert all(v.StatusCode.is_good() for v in seen.of("arm.Address"))
            assert len(seen.events) == 1  # nothing added or deleted: no event
            await until(lambda: len(seen.of("boom.Angles.pitch")) >= count + 5)
            await subscription.delete()
