"""Sparkplug B (docs/sparkplug.md) against a real mosquitto, every payload read by
Eclipse Tahu's decoder (npm ``sparkplug-payload``, run with Node: ``tahu.Tahu``), and
every command written with its encoder.  Expected values come from the simulator."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from support.broker import Mosquitto, Received, Recorder, recording
from support.derived import tilt
from support.harness import GROUP_OF, expected, running, tolerance, until
from support.tahu import Tahu

from imu_gateway.config import SensorConfig
from imu_gateway.frontends.sparkplug.host import HostState, read_state
from imu_gateway.frontends.sparkplug.metrics import device_rows
from imu_gateway.frontends.sparkplug.node import BdSeq, Device, EdgeNode, Ignored, Write
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GROUP, NODE = "plant", "gw1"
READING = Motion.from_seed(5).sample(3.0)
#: The decimals of the native sensors' BCD per group (the protocol document).
DIGITS = {"angles": 2, "accel": 4, "gyro": 2, "mag": 5, "quaternion": 6}
SP = "spBv1.0"


@pytest.fixture(scope="module")
def tahu() -> Iterator[Tahu]:
    codec = Tahu()
    yield codec
    codec.close()


def _config(port: str, broker: Mosquitto, poll_hz: float = 20, **sparkplug: Any
            ) -> dict[str, Any]:
    return {"gateway_id": NODE,
            "buses": [{"name": "a", "port": port, "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "poll_hz": poll_hz}]}],
            "mqtt": {"url": broker.url,
                     "sparkplug": {"group_id": GROUP, "plain_topics": False, **sparkplug}}}


def node_messages(rec: Recorder) -> list[Received]:
    """What the edge node published (not the test's own commands)."""
    return [m for m in list(rec.messages) if m.topic.startswith(f"{SP}/{GROUP}/")
            and kind(m) not in ("NCMD", "DCMD")]


def kind(m: Received) -> str:
    return m.topic.split("/")[2]


def decoded(tahu: Tahu, messages: list[Received]) -> list[tuple[str, dict[str, Any]]]:
    return [(kind(m), tahu.decode(m.payload)) for m in messages]


def metric(payload: dict[str, Any], name: str) -> dict[str, Any]:
    found: list[dict[str, Any]] = [m for m in payload["metrics"] if m.get("name") == name]
    assert len(found) == 1, (name, found)
    return found[0]



def _rebirth(tahu: Tahu) -> bytes:
    """An NCMD payload asking for a rebirth, as a host's Tahu encodes it."""
    return tahu.encode({"timestamp": int(time.time() * 1000), "metrics": [
        {"name": "Node Control/Rebirth", "type": "Boolean", "value": True}]})

@pytest.mark.anyio
async def test_births_data_aliases_and_values_as_tahu_reads_them(
        tmp_path: Path, tahu: Tahu) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        async with running(_config(line.path, broker)) as gw:
            assert gw.mqtt is None  # plain_topics: false
            await until(lambda: sum(kind(m) == "DDATA" for m in node_messages(rec)) >= 5)
        got = decoded(tahu, node_messages(rec))
    kinds = [k for k, _ in got]
    assert kinds[:2] == ["NBIRTH", "DBIRTH"] and kinds[-1] == "NDEATH"
    assert set(kinds[2:-1]) == {"DDATA"}
    nbirth, dbirth = got[0][1], got[1][1]
    assert metric(nbirth, "bdSeq")["value"] == 0 and metric(nbirth, "bdSeq")["type"] == "Int64"
    assert metric(nbirth, "Node Control/Rebirth")["value"] is False
    assert got[-1][1]["metrics"][0]["value"] == 0  # NDEATH's bdSeq: the birth's
    # seq: 0 in the NBIRTH, one more in each message after it; none in the NDEATH
    assert [p["seq"] for _, p in got[:-1]] == list(range(len(got) - 1))
    assert "seq" not in got[-1][1]
    # births name every metric, with alias and type; aliases are unique in the node
    aliases = {m["alias"]: m["name"] for _, p in got[:2] for m in p["metrics"]}
    assert len(aliases) == len(nbirth["metrics"]) + len(dbirth["metrics"])
    assert all("type" in m and "name" in m for m in dbirth["metrics"])
    units = {m["name"]: m["properties"]["engUnit"]["value"] for m in dbirth["metrics"]
             if "properties" in m}
    assert units["Angles/pitch"] == "°" and units["Acceleration/accel_x"] == "g"
    assert units["AngularRate/gyro_z"] == "°/s" and units["MagneticField/mag_x"] == "G"
    # values: the simulator's, as the sensor gave them (Double: no float32 widening)
    want = expected(ah)
    for name, value in want.items():
        (m,) = [m for m in dbirth["metrics"] if m["name"].endswith(f"/{name}")]
        assert m["type"] == "Double", m
        digits = DIGITS[GROUP_OF[name]]
        assert m["value"] == round(m["value"], digits), (name, m["value"])  # 32.52, exactly
        assert abs(m["value"] - value) <= tolerance(WireProtocol.NATIVE, name, value)
    # the derived values, from the pitch and roll the same birth carries
    pitch, roll = metric(dbirth, "Angles/pitch")["value"], metric(dbirth, "Angles/roll")["value"]
    assert (metric(dbirth, "Tilt/tilt")["value"], metric(dbirth, "Tilt/tilt_direction")[
        "value"]) == tilt(pitch, roll)
    assert metric(dbirth, "Tilt/tilt")["type"] == "Double"
    assert units["Tilt/tilt"] == "°" and units["Vibration/vibration"] == "g"
    assert metric(dbirth, "Vibration/vibration").get("value") in (None, 0.0)
    assert metric(dbirth, "Properties/Series")["value"] == "AH"
    # data: by alias only, known from the births, stamped with the sample's time
    for _, p in got[2:-1]:
        for m in p["metrics"]:
            assert "name" not in m and m["alias"] in aliases
            assert m["timestamp"] <= p["timestamp"]
    sequence = next(a for a, n in aliases.items() if n == "Status/Sequence")
    seqs = [m["value"] for _, p in got[2:-1] for m in p["metrics"] if m["alias"] == sequence]
    assert seqs == sorted(seqs) and len(seqs) >= 5


@pytest.mark.anyio
async def test_a_sparkplug_2_2_host_on_its_own_state_topic_is_heard(tmp_path: Path) -> None:
    """Sparkplug 2.2 hosts say ONLINE/OFFLINE on ``STATE/{host}``, outside the
    namespace: the node is born when one says ONLINE there."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        async with running(_config(line.path, broker, primary_host_id="scada")) as gw:
            await until(lambda: gw.sparkplug is not None and gw.sparkplug.connected)
            assert node_messages(rec) == []
            rec.client.publish("STATE/scada", b"ONLINE", 1, True)
            await until(lambda: any(kind(m) == "NBIRTH" for m in node_messages(rec)))


@pytest.mark.anyio
async def test_seq_wraps_and_an_ncmd_rebirth_births_again(tmp_path: Path, tahu: Tahu) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        async with running(_config(line.path, broker, poll_hz=0)):
            await until(lambda: len(node_messages(rec)) > 300, 60)
            rebirth = _rebirth(tahu)
            mark = len(node_messages(rec))
            rec.client.publish(f"{SP}/{GROUP}/NCMD/{NODE}", rebirth, qos=1)
            await until(lambda: any(kind(m) == "NBIRTH" for m in node_messages(rec)[mark:]))
            await until(lambda: any(kind(m) == "DDATA" for m in node_messages(rec)[mark:]))
        got = decoded(tahu, node_messages(rec))
    seqs = [p["seq"] for k, p in got if k != "NDEATH"]
    births = [i for i, (k, _) in enumerate(got) if k == "NBIRTH"]
    assert len(births) == 2
    first = seqs[:births[1]]
    assert first == [i % 256 for i in range(len(first))] and len(first) > 256  # wrapped
    again = got[births[1]:]
    assert [k for k, _ in again[:2]] == ["NBIRTH", "DBIRTH"]
    assert [p["seq"] for _, p in again[:2]] == [0, 1]
    assert metric(again[0][1], "bdSeq")["value"] == metric(got[0][1], "bdSeq")["value"]


@pytest.mark.anyio
async def test_a_sensor_offline_is_a_ddeath_and_back_a_dbirth(tmp_path: Path,
                                                             tahu: Tahu) -> None:
    faults = Faults()
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING),
                     faults=faults)
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        async with running(_config(line.path, broker)) as gw:
            await until(lambda: any(kind(m) == "DDATA" for m in node_messages(rec)))
            faults.stalled = True
            await until(lambda: any(kind(m) == "DDEATH" for m in node_messages(rec)), 30)
            assert not gw.cache.snapshot("boom").online
            faults.stalled = False
            await until(lambda: [kind(m) for m in node_messages(rec)].count("DBIRTH") == 2, 30)
        got = decoded(tahu, node_messages(rec))
    kinds = [k for k, _ in got]
    death = kinds.index("DDEATH")
    assert "DDATA" not in kinds[death + 1:kinds.index("DBIRTH", death)]
    seqs = [p["seq"] for k, p in got if k != "NDEATH"]
    assert seqs == [i % 256 for i in range(len(seqs))]


@pytest.mark.anyio
@pytest.mark.parametrize("allowed", [True, False])
async def test_a_dcmd_runs_the_command_only_when_allowed(tmp_path: Path, tahu: Tahu,
                                                         allowed: bool) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        async with running(_config(line.path, broker, allow_commands=allowed)) as gw:
            await until(lambda: any(kind(m) == "DBIRTH" for m in node_messages(rec)))
            dbirth = tahu.decode(next(m for m in node_messages(rec) if kind(m) == "DBIRTH").payload)
            names = {m["name"] for m in dbirth["metrics"]}
            assert ("Commands/set_zero_type" in names) is allowed
            write = tahu.encode({"timestamp": int(time.time() * 1000), "metrics": [
                {"name": "Commands/set_zero_type", "type": "String", "value": "relative"}]})
            rec.client.publish(f"{SP}/{GROUP}/DCMD/{NODE}/boom", write, qos=1)
            if allowed:
                await until(lambda: ah.settings.zero_type == "relative")
                result = metric(dbirth, "Commands/Result")["alias"]

                def said() -> list[Any]:
                    return [m["value"] for x in node_messages(rec) if kind(x) == "DDATA"
                            for m in tahu.decode(x.payload)["metrics"] if m["alias"] == result]

                await until(lambda: said() == ['set_zero_type: ok {"result": "success"}'])
            else:
                assert gw.sparkplug is not None
                await until(lambda: gw.sparkplug is not None and gw.sparkplug.ignored == 1)
                assert ah.settings.zero_type == "absolute"


@pytest.mark.anyio
async def test_births_wait_for_the_primary_host(tmp_path: Path, tahu: Tahu) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    state = f"{SP}/STATE/scada"
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        async with running(_config(line.path, broker, primary_host_id="scada")) as gw:
            await until(lambda: gw.cache.snapshot("boom").seq >= 5 and gw.sparkplug is not None
                        and gw.sparkplug.connected)
            assert node_messages(rec) == []  # no host yet: no birth
            # nor when a rebirth is asked for
            rebirth = _rebirth(tahu)
            rec.client.publish(f"{SP}/{GROUP}/NCMD/{NODE}", rebirth, qos=1)
            await until(lambda: gw.sparkplug is not None and gw.sparkplug.ignored == 1)
            assert node_messages(rec) == []
            rec.client.publish(state, json.dumps({"online": True, "timestamp": 1}), 1, True)
            await until(lambda: any(kind(m) == "DDATA" for m in node_messages(rec)))
            rec.client.publish(state, json.dumps({"online": False, "timestamp": 2}), 1, True)
            await until(lambda: any(kind(m) == "NDEATH" for m in node_messages(rec)))
            mark = len(node_messages(rec))
            await until(lambda: gw.sparkplug is not None and gw.sparkplug.counters.connects == 2)
            assert all(kind(m) != "NBIRTH" for m in node_messages(rec)[mark:])
            rec.client.publish(state, json.dumps({"online": True, "timestamp": 3}), 1, True)
            await until(lambda: sum(kind(m) == "NBIRTH" for m in node_messages(rec)) == 2)
        got = decoded(tahu, node_messages(rec))
    births = [metric(p, "bdSeq")["value"] for k, p in got if k == "NBIRTH"]
    deaths = [p["metrics"][0]["value"] for k, p in got if k == "NDEATH"]
    assert births == [0, 1] and deaths[0] == 0  # the session that ended, then a new one


def test_bdseq_goes_on_across_a_kill_9(tmp_path: Path, tahu: Tahu) -> None:
    """The gateway is killed (no goodbye): the broker publishes its will, an NDEATH
    whose bdSeq is its NBIRTH's; started again, it is born with the next bdSeq (kept
    in ``bdseq_file``), so a host never takes the old death for the new session's."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        config = tmp_path / "gateway.yaml"
        config.write_text(yaml.safe_dump(_config(line.path, broker,
                                                 bdseq_file=str(tmp_path / "bdseq"))))

        def births() -> list[int]:
            return [metric(tahu.decode(m.payload), "bdSeq")["value"]
                    for m in node_messages(rec) if kind(m) == "NBIRTH"]

        for run in range(2):
            gateway = subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c",
                                        str(config)], stderr=subprocess.DEVNULL)
            try:
                rec.wait(lambda r=run: len(births()) == r + 1, 30)  # type: ignore[misc]
            finally:
                gateway.send_signal(signal.SIGKILL)
                gateway.wait(10)
            rec.wait(lambda r=run: [kind(m) for m in node_messages(rec)].count("NDEATH")
                     == r + 1, 30)  # type: ignore[misc]
        deaths = [tahu.decode(m.payload)["metrics"][0]["value"] for m in node_messages(rec)
                  if kind(m) == "NDEATH"]
    first = births()[0]
    assert births() == [first, (first + 1) % 256] and deaths == births()
    assert (tmp_path / "bdseq").read_text().strip() == str(deaths[-1])


@pytest.mark.anyio
async def test_plain_topics_stay_alongside_unless_turned_off(tmp_path: Path) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, "#") as rec:
        config = _config(line.path, broker)
        config["mqtt"]["sparkplug"]["plain_topics"] = True
        async with running(config) as gw:
            assert gw.mqtt is not None and gw.sparkplug is not None
            await until(lambda: bool(rec.on(f"imu/{NODE}/boom/state")) and
                        any(kind(m) == "DDATA" for m in node_messages(rec)))


# ------------------------------------------------------------------ sans-IO rules


def _node(tmp_path: Path | None = None) -> EdgeNode:
    sensor = SensorConfig(name="boom", series=Series.AH, address=0)
    rows = tuple(device_rows(sensor, WireProtocol.NATIVE, commands=True))
    return EdgeNode(GROUP, NODE, [Device("boom", rows)],
                    BdSeq(tmp_path / "bdseq" if tmp_path else None))


def test_bdseq_is_kept_and_wraps_at_256(tmp_path: Path) -> None:
    node = _node(tmp_path)
    assert [node.bdseq.next() for _ in range(3)] == [0, 1, 2]
    assert _node(tmp_path).bdseq.next() == 3  # a restart goes on from the kept one
    (tmp_path / "bdseq").write_text("255\n")
    assert _node(tmp_path).bdseq.next() == 0
    (tmp_path / "bdseq").write_text("garbage")
    assert _node(tmp_path).bdseq.next() == 0  # unreadable: a fresh start
    assert _node().bdseq.next() == 0  # no file: each start from 0


def test_a_bdseq_that_cannot_be_kept_goes_on_in_memory(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A full or read-only disk must not end the session (the will needs the number):
    it goes on counting, and the failure is said once."""
    (tmp_path / "a-file").write_text("")
    bdseq = BdSeq(tmp_path / "a-file" / "bdseq")  # its folder is a file: never written
    with caplog.at_level("ERROR", logger="imu_gateway.sparkplug"):
        assert [bdseq.next() for _ in range(3)] == [0, 1, 2]
    said = [r.getMessage() for r in caplog.records if "cannot keep bdSeq" in r.getMessage()]
    assert len(said) == 1, said


def test_commands_that_are_not_acted_on_say_why(tahu: Tahu) -> None:
    node = _node()
    dcmd = f"{SP}/{GROUP}/DCMD/{NODE}/boom"
    assert isinstance(node.command(dcmd, b"\xff\xff\xff"), Ignored)  # not protobuf
    other = f"{SP}/{GROUP}/DCMD/{NODE}/nobody"
    zero = tahu.encode({"metrics": [{"name": "Commands/set_zero_type", "type": "String",
                                     "value": "relative"}]})
    assert "unknown device" in str(node.command(other, zero))
    value = tahu.encode({"metrics": [{"name": "Angles/pitch", "type": "Float", "value": 1.0}]})
    assert "not a command metric" in str(node.command(dcmd, value))
    false = tahu.encode({"metrics": [{"name": "Commands/save", "type": "Boolean",
                                      "value": False}]})
    assert "write true" in str(node.command(dcmd, false))
    assert node.command(dcmd, zero) == [Write("boom", "set_zero_type", "relative")]
    degrees = tahu.encode({"metrics": [{"name": "Commands/set_declination",
                                        "type": "Double", "value": -3.5}]})
    assert node.command(dcmd, degrees) == [Write("boom", "set_declination", -3.5)]
    no_rebirth = tahu.encode({"metrics": [{"name": "Node Control/Rebirth", "type": "Boolean",
                                           "value": False}]})
    assert isinstance(node.command(f"{SP}/{GROUP}/NCMD/{NODE}", no_rebirth), Ignored)


def test_a_primary_host_state_is_read_in_both_spellings() -> None:
    assert read_state(b'{"online": true, "timestamp": 1}', False) == HostState(True, 1, False)
    assert read_state(b'{"online": false, "timestamp": 1}', False) == HostState(False, 1, False)
    assert read_state(b"ONLINE", True) == HostState(True, None, True)  # Sparkplug 2.2
    assert read_state(b"OFFLINE", True) == HostState(False, None, True)
    assert "boolean" in str(read_state(b'{"online": "yes"}', False))
    assert "neither" in str(read_state(b"\xff", False))


@pytest.mark.anyio
async def test_every_metric_is_stamped_and_refused_writes_and_settings_are_answered(
        tmp_path: Path, tahu: Tahu) -> None:
    """Every metric has a timestamp (the NBIRTH's bdSeq and rebirth, a command's
    result too); a DCMD of the wrong datatype is answered in ``Commands/Result``, like
    a command the sensor refused; ``read_settings`` answers with the settings; the
    buses' counters are node metrics, in the NBIRTH and then an NDATA of what changed."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    dcmd = f"{SP}/{GROUP}/DCMD/{NODE}/boom"
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as rec:
        async with running(_config(line.path, broker, allow_commands=True)):
            await until(lambda: any(kind(m) == "DBIRTH" for m in node_messages(rec)))
            (dbirth,) = [tahu.decode(m.payload) for m in node_messages(rec)
                         if kind(m) == "DBIRTH"]
            result = metric(dbirth, "Commands/Result")["alias"]

            def said() -> list[Any]:
                return [m["value"] for x in node_messages(rec) if kind(x) == "DDATA"
                        for m in tahu.decode(x.payload)["metrics"] if m["alias"] == result]

            wrong = tahu.encode({"timestamp": int(time.time() * 1000), "metrics": [
                {"name": "Commands/set_address", "type": "String", "value": "7"}]})
            rec.client.publish(dcmd, wrong, qos=1)
            await until(lambda: len(said()) == 1)
            assert said()[0] == ("set_address: bad_arguments: Commands/set_address is Int32; "
                                 "the DCMD wrote a String")
            assert ah.address == 0
            read = tahu.encode({"timestamp": int(time.time() * 1000), "metrics": [
                {"name": "Commands/read_settings", "type": "Boolean", "value": True}]})
            rec.client.publish(dcmd, read, qos=1)
            await until(lambda: len(said()) == 2)
            assert said()[1].startswith("read_settings: ok {")
            settings = json.loads(said()[1].removeprefix("read_settings: ok "))
            assert settings["zero_type"] == "absolute" and settings["address"] == 0
            await until(lambda: any(kind(m) == "NDATA" for m in node_messages(rec)), 20)
        got = decoded(tahu, node_messages(rec))
    nbirth = got[0][1]
    assert metric(nbirth, "Buses/a/Transactions")["type"] == "UInt64"
    assert metric(nbirth, "Buses/a/Errors/timeout")["value"] == 0
    assert 0 <= metric(nbirth, "Buses/a/Utilisation")["value"] <= 1
    transactions = metric(nbirth, "Buses/a/Transactions")["alias"]
    ndata = [p for k, p in got if k == "NDATA"]
    assert any(m["alias"] == transactions and m["value"] > 0 for m in ndata[0]["metrics"])
    for k, payload in got:
        for m in payload["metrics"]:
            assert isinstance(m.get("timestamp"), int) and m["timestamp"] > 0, (k, m)
