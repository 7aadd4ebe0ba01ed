"""Alarms over Sparkplug B (docs/sparkplug.md, "Alarms"; docs/alarms.md) against a
real mosquitto and the running gateway on a simulated sensor, every payload read by
Eclipse Tahu's decoder and every DCMD written with its encoder, as a host would: the
alarm metrics in the DBIRTH, a lean past the limit raising the alarm after its
on-delay in a DDATA of its own, an acknowledgement by DCMD, the hysteresis holding it,
and the DCMD refused while commands are not allowed.

Waits are for messages and samples, never for a fixed time."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from support.broker import Mosquitto, Received, Recorder, recording
from support.harness import running, until
from support.tahu import Tahu

from imu_gateway.app import Gateway
from imu_gateway.config import SensorConfig
from imu_gateway.frontends.sparkplug.metrics import device_rows
from imu_gateway.frontends.sparkplug.node import (
    Acknowledge,
    BdSeq,
    Device,
    EdgeNode,
    Ignored,
    Refused,
)
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import (
    Faults,
    SimSensor,
    SimulatorThread,
    hold,
    make_sensor,
    simulated,
)
from imu_gateway.simulator.motion import Motion

GROUP, NODE, SP = "plant", "gw1", "spBv1.0"
DCMD = f"{SP}/{GROUP}/DCMD/{NODE}/boom"
ON_DELAY = 0.3
SLACK_MS = 20
LEAN = "Alarms/boom_lean"


@pytest.fixture(scope="module")
def tahu() -> Iterator[Tahu]:
    codec = Tahu()
    yield codec
    codec.close()


@pytest.fixture
def faults() -> Faults:
    return Faults()


@pytest.fixture
def boom(faults: Faults) -> Iterator[tuple[SimSensor, SimulatorThread]]:
    """An AH held level but for a 1° pitch (tilt 1°), before the gateway starts."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200,
                     source=hold(Motion.from_seed(5).sample(3.0)), faults=faults)
    with simulated([ah]) as line:
        line.call(ah.lean, 1.0, 0.0).result(5)
        yield ah, line


def config(port: str, broker: Mosquitto, allow_commands: bool) -> dict[str, Any]:
    alarms = [{"name": "boom_lean", "field": "tilt", "above": 5.0, "hysteresis": 0.5,
               "on_delay_s": ON_DELAY, "severity": "critical"},
              {"name": "boom_low", "field": "pitch", "below": -30.0, "severity": "info"}]
    return {"gateway_id": NODE,
            "buses": [{"name": "a", "port": port, "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "poll_hz": 20,
                                    "alarms": alarms}]}],
            "mqtt": {"url": broker.url,
                     "sparkplug": {"group_id": GROUP, "plain_topics": False,
                                   "allow_commands": allow_commands}}}


def kind(m: Received) -> str:
    return m.topic.split("/")[2]


class Host:
    """The node's messages as a host reads them: each decoded by Tahu once, in order,
    and each metric of a DDATA named through the aliases of the births."""

    def __init__(self, rec: Recorder, tahu: Tahu) -> None:
        self.rec, self.tahu = rec, tahu
        self.got: list[tuple[str, dict[str, Any]]] = []
        self.names: dict[int, str] = {}

    def read(self) -> list[tuple[str, dict[str, Any]]]:
        mine = [m for m in list(self.rec.messages) if m.topic.startswith(f"{SP}/{GROUP}/")
                and kind(m) not in ("NCMD", "DCMD")]
        for m in mine[len(self.got):]:
            payload = self.tahu.decode(m.payload)
            if kind(m) in ("NBIRTH", "DBIRTH"):
                self.names.update({x["alias"]: x["name"] for x in payload["metrics"]})
            self.got.append((kind(m), payload))
        return self.got

    def dbirth(self) -> dict[str, dict[str, Any]]:
        """The first DBIRTH's metrics, by name."""
        payload = next(p for k, p in self.read() if k == "DBIRTH")
        return {m["name"]: m for m in payload["metrics"]}

    def ddata(self) -> list[dict[str, dict[str, Any]]]:
        """Every DDATA's metrics, by name."""
        return [{self.names[m["alias"]]: m for m in p["metrics"]}
                for k, p in self.read() if k == "DDATA"]

    def transitions(self, alarm: str = LEAN) -> list[dict[str, dict[str, Any]]]:
        """The DDATAs that carry the alarm's metrics."""
        return [d for d in self.ddata() if any(n.startswith(f"{alarm}/") for n in d)]

    def results(self) -> list[str]:
        return [d["Commands/Result"]["value"] for d in self.ddata() if "Commands/Result" in d]

    def ack(self, value: Any = True, datatype: str = "Boolean", alarm: str = LEAN) -> None:
        write = self.tahu.encode({"timestamp": int(time.time() * 1000), "metrics": [
            {"name": f"{alarm}/Acked", "type": datatype, "value": value}]})
        self.rec.client.publish(DCMD, write, qos=1)


async def samples_pass(gateway: Gateway, host: Host, n: int = 3) -> None:
    """Wait until ``n`` more samples of the boom have been evaluated, and the host has
    the DDATA of the last: whatever the node sent before it has arrived too (one
    session's messages keep their order)."""
    seq = gateway.cache.snapshot("boom").seq + n
    await until(lambda: gateway.cache.snapshot("boom").seq >= seq)
    await until(lambda: any(d.get("Status/Sequence", {}).get("value", 0) >= seq
                            for d in host.ddata()))


def values(data: dict[str, dict[str, Any]]) -> dict[str, Any]:
    return {name.rsplit("/", 1)[-1]: m["value"] for name, m in data.items()}


@pytest.mark.anyio
async def test_a_lean_raises_the_alarm_in_ddata_after_its_on_delay_and_a_dcmd_acks_it(
        tmp_path: Path, tahu: Tahu, boom: tuple[SimSensor, SimulatorThread]) -> None:
    ah, line = boom
    with Mosquitto(tmp_path) as broker, recording(broker, f"{SP}/#") as rec:
        host = Host(rec, tahu)
        async with running(config(line.path, broker, allow_commands=True)) as gw:
            await until(lambda: any(k == "DBIRTH" for k, _ in host.read()))
            birth = host.dbirth()
            # every alarm in the DBIRTH, named, typed, in the gateway's order
            # (configured ones first, the communication alarm last)
            alarm_names = [n for n in birth if n.startswith("Alarms/")]
            assert alarm_names == [f"Alarms/{a}/{m}" for a in
                                   ("boom_lean", "boom_low", "communication")
                                   for m in ("Active", "Acked", "State", "Severity")]
            assert {n: (birth[n]["type"], birth[n]["value"]) for n in alarm_names
                    if n.startswith(LEAN)} == {
                f"{LEAN}/Active": ("Boolean", False), f"{LEAN}/Acked": ("Boolean", True),
                f"{LEAN}/State": ("String", "normal"), f"{LEAN}/Severity": ("String",
                                                                           "critical")}
            assert birth["Alarms/boom_low/Severity"]["value"] == "info"
            assert birth["Alarms/communication/Severity"]["value"] == "critical"
            assert birth["Alarms/communication/State"]["value"] == "normal"

            leaned_at = time.time()
            line.call(ah.lean, 7.5, 0.0).result(5)
            await until(lambda: len(host.transitions()) == 1)
            (raised,) = host.transitions()
            # a DDATA of its own, with what changed, stamped with the transition's time
            assert values(raised) == {"Active": True, "Acked": False,
                                      "State": "active_unacked"}
            stamps = {m["timestamp"] for m in raised.values()}
            assert len(stamps) == 1
            raised_ms = stamps.pop()
            # the on-delay: the reading of 7.5 came first, and the alarm only once the
            # lean had held for it (the delay runs on the monotonic clock, the stamps
            # are the samples' wall times: a few ms of slack for a loaded machine)
            leaned = [d for d in host.ddata() if d.get("Tilt/tilt", {}).get("value") == 7.5]
            first = leaned[0]["Tilt/tilt"]["timestamp"]
            assert raised_ms >= first + ON_DELAY * 1000 - SLACK_MS
            assert raised_ms >= (leaned_at + ON_DELAY) * 1000 - SLACK_MS
            assert gw.alarm_states()[0].state.value == "active_unacked"

            # refused writes: answered, acknowledge nothing
            host.ack(False)
            host.ack("yes", "String")
            await until(lambda: len(host.results()) == 2)
            assert host.results() == [
                f"{LEAN}/Acked: bad_arguments: {LEAN}/Acked is Boolean: write true to "
                "acknowledge (the DCMD wrote false)",
                f"{LEAN}/Acked: bad_arguments: {LEAN}/Acked is Boolean: write true to "
                "acknowledge (the DCMD wrote a String)"]
            assert len(host.transitions()) == 1

            host.ack()
            await until(lambda: len(host.results()) == 3)
            assert host.results()[2] == f"{LEAN}/Acked: ok"
            acked = host.transitions()[1]
            assert values(acked) == {"Acked": True, "State": "active_acked"}
            # the transition came before the answer
            data = host.ddata()
            answered = next(i for i, d in enumerate(data)
                            if d.get("Commands/Result", {}).get("value") == f"{LEAN}/Acked: ok")
            assert data.index(acked) < answered
            assert gw.alarm_journal()[-1].by == "sparkplug DCMD"
            host.ack()
            await until(lambda: len(host.results()) == 4)
            assert host.results()[3] == (
                f"{LEAN}/Acked: nothing_to_acknowledge: boom/boom_lean is acknowledged "
                "already: nothing to acknowledge")

            # inside the limit but not through the hysteresis (4.7 > 4.5): still active
            line.call(ah.lean, 4.7, 0.0).result(5)
            await until(lambda: any(d.get("Tilt/tilt", {}).get("value") == 4.7
                                    for d in host.ddata()))
            await samples_pass(gw, host)
            assert len(host.transitions()) == 2
            line.call(ah.lean, 4.0, 0.0).result(5)
            await until(lambda: len(host.transitions()) == 3)
            assert values(host.transitions()[2]) == {"Active": False, "State": "normal"}
        got = host.read()
    assert all(m["timestamp"] > 0 for _, p in got for m in p["metrics"])
    seqs = [p["seq"] for k, p in got if k != "NDEATH"]
    assert seqs == [i % 256 for i in range(len(seqs))]


@pytest.mark.anyio
async def test_an_ack_by_dcmd_is_refused_while_commands_are_not_allowed(
        tmp_path: Path, tahu: Tahu, boom: tuple[SimSensor, SimulatorThread]) -> None:
    ah, line = boom
    with Mosquitto(tmp_path) as broker, recording(broker, f"{SP}/#") as rec:
        host = Host(rec, tahu)
        async with running(config(line.path, broker, allow_commands=False)) as gw:
            await until(lambda: any(k == "DBIRTH" for k, _ in host.read()))
            birth = host.dbirth()
            assert birth[f"{LEAN}/Acked"]["type"] == "Boolean"  # shown, not writable
            assert "Commands/Result" not in birth
            line.call(ah.lean, 7.5, 0.0).result(5)
            await until(lambda: len(host.transitions()) == 1)
            assert gw.sparkplug is not None
            host.ack()
            await until(lambda: gw.sparkplug is not None and gw.sparkplug.ignored == 1)
            await samples_pass(gw, host)
            assert [s.state.value for s in gw.alarm_states() if s.name == "boom_lean"] == \
                ["active_unacked"]
            assert [t.to_state.value for t in gw.alarm_journal()] == ["active_unacked"]
            assert len(host.transitions()) == 1


@pytest.mark.anyio
async def test_the_communication_alarm_in_ddata_while_born_and_in_the_next_dbirth(
        tmp_path: Path, tahu: Tahu, boom: tuple[SimSensor, SimulatorThread],
        faults: Faults) -> None:
    """A sensor that stops answering is stale first (its device still born: the
    communication alarm goes out in DDATA), then offline (DDEATH); back, its DBIRTH
    has the alarm still active, and its clearing follows in a DDATA; a DCMD
    acknowledges it."""
    _, line = boom
    comm = "Alarms/communication"
    with Mosquitto(tmp_path) as broker, recording(broker, f"{SP}/#") as rec:
        host = Host(rec, tahu)
        settings = config(line.path, broker, allow_commands=True)
        settings["buses"][0]["sensors"][0]["stale_after_ms"] = 400
        async with running(settings):
            await until(lambda: any(k == "DDATA" for k, _ in host.read()))
            mark = len(host.read())
            faults.stalled = True
            await until(lambda: any(k == "DDEATH" for k, _ in host.read()[mark:]), 30)
            got = host.read()
            death = next(i for i, (k, _) in enumerate(got) if i >= mark and k == "DDEATH")
            before = [{host.names[m["alias"]]: m["value"] for m in p["metrics"]}
                      for k, p in got[mark:death] if k == "DDATA"]
            assert {f"{comm}/Active": True, f"{comm}/Acked": False,
                    f"{comm}/State": "active_unacked"} in before
            faults.stalled = False
            await until(lambda: any(k == "DBIRTH" for k, _ in host.read()[death:]), 30)
            birth = next(p for k, p in host.read()[death:] if k == "DBIRTH")
            shown = {m["name"]: m["value"] for m in birth["metrics"]}
            assert (shown[f"{comm}/Active"], shown[f"{comm}/State"]) == (True, "active_unacked")

            def cleared() -> bool:
                after = host.read()[death:]
                return any(m.get("value") == "rtn_unacked" and
                           host.names[m["alias"]] == f"{comm}/State"
                           for k, p in after if k == "DDATA" for m in p["metrics"])

            await until(cleared)
            host.ack(alarm=comm)
            await until(lambda: f"{comm}/Acked: ok" in host.results())
            assert values(host.transitions(comm)[-1]) == {"Acked": True, "State": "normal"}


# ------------------------------------------------------------------ sans-IO rules


def _node() -> EdgeNode:
    devices = [Device(name, tuple(device_rows(SensorConfig(name=name, series=Series.AH,
                                                           address=i),
                                              WireProtocol.NATIVE, commands=True)),
                      ("boom_lean", "communication"))
               for i, name in enumerate(("boom", "mast"))]
    return EdgeNode(GROUP, NODE, devices, BdSeq(None))


def test_an_ack_is_a_true_written_to_the_alarms_own_acked(tahu: Tahu) -> None:
    node = _node()

    def write(metric: dict[str, Any], device: str = "boom") -> object:
        outcome = node.command(f"{SP}/{GROUP}/DCMD/{NODE}/{device}",
                               tahu.encode({"metrics": [metric]}))
        assert isinstance(outcome, list) and len(outcome) == 1, outcome
        return outcome[0]

    acked = {"name": f"{LEAN}/Acked", "type": "Boolean", "value": True}
    assert write(acked) == Acknowledge("boom", "boom_lean", f"{LEAN}/Acked")
    assert write({**acked, "name": "Alarms/communication/Acked"}) == \
        Acknowledge("boom", "communication", "Alarms/communication/Acked")
    by_alias = node.alias["boom", f"{LEAN}/Acked"]
    assert write({"alias": by_alias, "type": "Boolean", "value": True}) == \
        Acknowledge("boom", "boom_lean", f"{LEAN}/Acked")
    # another device's alias, written to this one: not this device's metric
    other = write({"alias": node.alias["mast", f"{LEAN}/Acked"], "type": "Boolean",
                   "value": True})
    assert isinstance(other, Refused) and other.kind.value == "unknown_command"
    for metric in ({**acked, "name": f"{LEAN}/Active"}, {**acked, "name": "Alarms/nope/Acked"}):
        refused = write(metric)
        assert isinstance(refused, Refused) and refused.kind.value == "unknown_command"
        assert "Alarms/{alarm}/Acked" in refused.reason
    assert not isinstance(node.command(DCMD, b"\xff"), list)
    assert isinstance(node.command(DCMD, b"\xff"), Ignored)
