"""MQTT (docs/mqtt.md, issue 5) against a real mosquitto broker.

Every test starts its own broker (``broker.Mosquitto``) on a free port and listens
with a paho client of its own (``broker.Recorder``).  The gateway runs on simulated
sensors on real pseudo-terminals.  Expected values come from the simulator and
docs/mqtt.md, never from the gateway's MQTT module.  Waits are deadlines on a condition.
"""

from __future__ import annotations

import asyncio
import gc
import itertools
import json
import logging
import re
import signal
import subprocess
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest
import yaml
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties
from prometheus_client import CollectorRegistry, generate_latest
from support.broker import Mosquitto, Recorder, Tls, make_tls, recording
from support.derived import tilt
from support.harness import (
    FIELDS,
    GROUP_OF,
    expected,
    fields_of,
    interrupt,
    running,
    tolerance,
    until,
)

from imu_gateway.app import Gateway
from imu_gateway.frontends.mqtt.states import StateDesk
from imu_gateway.frontends.rest.metrics import GatewayCollector
from imu_gateway.model import Angles, Series, WireProtocol
from imu_gateway.mqtt_link.message import Message
from imu_gateway.simulator import Faults, SimSensor, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
READING = Motion.from_seed(3).sample(10.0)
GID = "test"
BASE = f"imu/{GID}"
# Which groups each series' state JSON carries (an AH measures all five, a VG no mag).
GROUPS = {Series.AH: {"angles", "accel", "gyro", "mag", "quaternion", "tilt", "vibration"},
          Series.VG: {"angles", "accel", "gyro", "quaternion", "tilt", "vibration"}}
DERIVED = {"tilt", "tilt_direction", "vibration"}


def sensor(protocol: WireProtocol, series: Series, **options: Any) -> SimSensor:
    return make_sensor(protocol, series, baud=FAST, **options)


def bus(name: str, port: str, protocol: str, sensors: list[dict[str, Any]]) -> dict[str, Any]:
    return {"name": name, "port": port, "baudrate": FAST, "protocol": protocol,
            "timeout_ms": 300, "sensors": sensors}


def config(buses: list[dict[str, Any]], broker: Mosquitto, **mqtt: Any) -> dict[str, Any]:
    return {"gateway_id": GID, "buses": buses, "mqtt": {"url": broker.url, **mqtt}}


def state(message: Any) -> dict[str, Any]:
    value = json.loads(message.payload)
    assert isinstance(value, dict)
    return value




def written(gateway: Gateway) -> bool:
    """Every message the gateway made so far is on its way to the broker (after this, a
    new subscriber sees what it retained)."""
    mqtt = gateway.mqtt
    return mqtt is not None and mqtt.connected and not mqtt.outbox and \
        mqtt.stats()["in_flight"] == 0


def retained(broker: Mosquitto, topic: str, **options: Any) -> list[Any]:
    """The retained messages a new subscriber to ``topic`` gets."""
    with recording(broker, topic, **options) as fresh:
        # Retained messages come right after the SUBACK; a round trip of our own
        # message through the broker proves they are all in.  At QoS 1, so that it
        # queues behind them: the broker holds back QoS 1 messages past its in-flight
        # limit (20), and a QoS 0 one would overtake them.
        marker = f"{BASE}/_marker"
        fresh.client.subscribe(marker, qos=1)
        fresh.client.publish(marker, b"x", qos=1)
        fresh.wait(lambda: fresh.on(marker))
        return [m for m in fresh.messages if m.retain]


async def nothing_retained(broker: Mosquitto, topic: str) -> bool:
    return not await asyncio.to_thread(retained, broker, topic)


# ------------------------------------------------------------------ state and status


@pytest.mark.anyio
async def test_state_json_carries_the_simulators_values(tmp_path: Path) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    vg = sensor(WireProtocol.MODBUS, Series.VG, address=1, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line_a, \
            simulated([vg]) as line_b, recording(broker, "imu/#") as rec:
        cfg = config([bus("a", line_a.path, "native", [{"name": "boom", "series": "AH"}]),
                      bus("b", line_b.path, "modbus", [{"name": "arm", "series": "VG"}])],
                     broker)

        async with running(cfg):
            await until(lambda: bool(rec.on(f"{BASE}/boom/state")
                                     and rec.on(f"{BASE}/arm/state")))

        for name, sim, protocol in (("boom", ah, WireProtocol.NATIVE),
                                    ("arm", vg, WireProtocol.MODBUS)):
            message = rec.on(f"{BASE}/{name}/state")[-1]
            got = state(message)
            assert set(got) == {"sensor", "ts", "seq", "status"} | GROUPS[sim.series]
            assert got["sensor"] == name and got["status"] == "ok" and got["seq"] >= 1
            assert got["ts"].endswith("Z") and len(got["ts"]) == len("2026-11-22T03:40:00.123Z")
            want = expected(sim)
            for field_name, value in fields_of(got).items():
                assert abs(value - want[field_name]) <= tolerance(protocol, field_name, value), \
                    (name, field_name, value, want[field_name])
            # the derived values, from the values the same message carries
            angles = got["angles"]
            assert (got["tilt"]["tilt"], got["tilt"]["tilt_direction"]) == \
                tilt(angles["pitch"], angles["roll"])
            assert got["vibration"]["vibration"] in (None, 0.0)  # held still: 0 once known
            assert message.retain is False  # live delivery; retained copies are checked below
            assert "online" in [m.text for m in rec.on(f"{BASE}/{name}/availability")]
        assert [m.text for m in rec.on(f"{BASE}/status")] == ["online", "offline"]
        assert rec.on(f"{BASE}/boom/availability")[-1].text == "offline"


@pytest.mark.anyio
async def test_status_availability_and_state_are_retained(tmp_path: Path) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])], broker)

        async with running(cfg) as gateway:
            await until(lambda: gateway.cache.snapshot("boom").seq >= 2)
            await until(lambda: written(gateway))
            kept = {m.topic: m for m in await asyncio.to_thread(retained, broker, "imu/#")}
            assert kept[f"{BASE}/status"].text == "online"
            assert kept[f"{BASE}/boom/availability"].text == "online"
            assert state(kept[f"{BASE}/boom/state"])["sensor"] == "boom"
        kept = {m.topic: m for m in await asyncio.to_thread(retained, broker, "imu/#")}
        assert kept[f"{BASE}/status"].text == "offline"  # said on a clean stop
        assert kept[f"{BASE}/boom/availability"].text == "offline"



@pytest.mark.anyio
async def test_availability_follows_a_sensor_that_stops_and_comes_back(tmp_path: Path) -> None:
    faults = Faults()
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING), faults=faults)
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{BASE}/boom/#") as rec:
        cfg = config([bus("a", line.path, "native",
                          [{"name": "boom", "series": "AH", "poll_hz": 20}])], broker)
        availability = f"{BASE}/boom/availability"

        def said() -> list[str]:
            return [m.text for m in rec.on(availability)]

        async with running(cfg):
            await until(lambda: said()[-1:] == ["online"])
            faults.stalled = True
            await until(lambda: said()[-1:] == ["offline"])
            # the state says it too (sent just after the availability)
            await until(lambda: state(rec.on(f"{BASE}/boom/state")[-1])["status"]
                        == "offline")
            faults.stalled = False
            await until(lambda: said()[-1:] == ["online"], timeout=20)
            await until(lambda: state(rec.on(f"{BASE}/boom/state")[-1])["status"] == "ok")

        # (an "offline" may come first: the gateway's view before its first poll)
        changes = said()[said().index("online"):]
        assert changes == ["online", "offline", "online", "offline"]  # the last: stopping


# ------------------------------------------------------------------ commands


def _registry(collector: GatewayCollector) -> CollectorRegistry:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    return registry


@pytest.mark.anyio
@pytest.mark.parametrize("version", ["3.1.1", "5"])
async def test_command_round_trip(tmp_path: Path, version: str,
                            caplog: pytest.LogCaptureFixture) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    vg = sensor(WireProtocol.NATIVE, Series.VG, address=1, source=hold(READING))
    paho_version = paho.MQTTv5 if version == "5" else paho.MQTTv311
    with Mosquitto(tmp_path) as broker, simulated([ah, vg]) as line, \
            recording(broker, f"{BASE}/+/cmd/+/result", "replies/#",
                      version=paho_version) as rec:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"},
                                                     {"name": "arm", "series": "VG",
                                                      "address": 1}])],
                     broker, allow_commands=True, protocol=version)
        cmd = f"{BASE}/boom/cmd"

        async def ask(topic: str, payload: str | bytes, **options: Any) -> dict[str, Any]:
            result_topic = options.pop("result_topic", f"{topic}/result")
            before = len(rec.on(result_topic))
            rec.client.publish(topic, payload, qos=1, **options)
            await until(lambda: len(rec.on(result_topic)) > before)
            return state(rec.on(result_topic)[-1])

        async with running(cfg) as gateway:
            # (connected is not enough: a command sent before the broker granted the
            # subscription has no subscriber, and the broker drops it)
            await until(lambda: gateway.mqtt is not None and gateway.mqtt.taking_commands)
            await until(lambda: gateway.cache.snapshot("boom").seq >= 1)
            result = await ask(f"{cmd}/set_zero_type", '{"type": "relative"}')
            assert result["ok"] is True and result["error"] is None
            assert ah.settings.zero_type == "relative"
            result = await ask(f"{cmd}/read_settings", "{}")
            assert result["ok"] is True
            assert result["answer"]["zero_type"] == "relative"

            # Bad requests: each answered with an error, nothing stops.
            bad = await ask(f"{cmd}/set_zero_type", "{not json")
            assert bad["ok"] is False and bad["kind"] == "bad_arguments"
            assert "not JSON" in bad["error"]
            bad = await ask(f"{cmd}/set_zero_type", "[1, 2]")
            assert bad["kind"] == "bad_arguments" and "JSON object" in bad["error"]
            bad = await ask(f"{cmd}/set_zero_type", '{"type": "sideways"}')
            assert bad["kind"] == "bad_arguments" and "type" in bad["error"]
            bad = await ask(f"{cmd}/explode", "{}")
            assert bad["kind"] == "unknown_command"
            bad = await ask(f"{BASE}/arm/cmd/set_declination", '{"degrees": 3}')
            assert bad["kind"] == "unsupported"
            bad = await ask(f"{BASE}/nobody/cmd/save", "{}")
            assert bad["ok"] is False and "nobody" in bad["error"]
            assert bad["kind"] == "unknown_sensor"  # as REST says it
            bad = await ask(f"{cmd}/set_zero_type", b"\xff\xfe")
            assert bad["kind"] == "bad_arguments"
            bad = await ask(f"{cmd}/set_zero_type", "[" * 100_000)  # too deep to parse
            assert bad["kind"] == "bad_arguments"
            # in-band correlation, for clients without MQTT 5 properties
            tagged = await ask(f"{cmd}/set_zero_type",
                               '{"type": "relative", "request_id": "req-7"}')
            assert tagged["ok"] is True and tagged["request_id"] == "req-7"
            tagged = await ask(f"{cmd}/set_zero_type", '{"type": 5, "request_id": 42}')
            assert tagged["kind"] == "bad_arguments" and tagged["request_id"] == 42
            tagged = await ask(f"{cmd}/read_settings", '{"request_id": [1]}')
            assert tagged["kind"] == "bad_arguments" and "request_id" in tagged["error"]
            # what the client counted, on /metrics
            metrics = generate_latest(_registry(GatewayCollector(gateway))).decode()
            assert re.search(r"^imu_gateway_mqtt_commands_total (\d+)", metrics, re.M)
            errors = re.search(r"^imu_gateway_mqtt_command_errors_total (\d+)", metrics, re.M)
            assert errors and float(errors.group(1)) >= 9
            assert re.search(r"^imu_gateway_mqtt_connects_total 1", metrics, re.M)
            assert re.search(r"^imu_gateway_mqtt_queue_depth \d", metrics, re.M)

            await _retained_commands(broker, rec, cmd, version, ah, ask)

            if version == "5":
                # paho's Properties.__init__ is unannotated
                props = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
                props.ResponseTopic = "replies/me"
                props.CorrelationData = b"req-42"
                result = await ask(f"{cmd}/read_settings", "{}", properties=props,
                                   result_topic="replies/me")
                assert result["ok"] is True
                answer = rec.on("replies/me")[-1]
                assert answer.properties.CorrelationData == b"req-42"

        # A retained command left on the broker (published while no gateway ran)
        # is not run when the broker replays it, and the gateway clears it.
        rec.client.publish(f"{cmd}/set_zero_type", '{"type": "absolute"}', qos=1,
                           retain=True).wait_for_publish(10)
        before = len(rec.on(f"{cmd}/set_zero_type/result"))
        async with running(cfg) as gateway:  # subscribes anew: the broker replays
            await until(lambda: gateway.mqtt is not None and gateway.mqtt.connected)
            await until(lambda: any("retained command" in r.getMessage()
                                    for r in caplog.records))
            await until(lambda: nothing_retained(broker, f"{cmd}/+"))
        assert ah.settings.zero_type == "relative"
        assert len(rec.on(f"{cmd}/set_zero_type/result")) == before



Ask = Callable[..., Awaitable[dict[str, Any]]]


async def _retained_commands(broker: Mosquitto, rec: Recorder, cmd: str, version: str,
                             ah: SimSensor, ask: Ask) -> None:
    """What comes with the retain flag, or empty, is never run as a command."""
    writes = ah.writes_heard.copy()
    # Clearing a retained command (an empty retained message): nothing runs, no result.
    rec.client.publish(f"{cmd}/save", b"", qos=1, retain=True).wait_for_publish(10)
    rec.client.publish(f"{cmd}/save", b"", qos=1).wait_for_publish(10)
    if version == "5":
        # MQTT 5 shows the retain flag of a live message: never run, and cleared.
        rec.client.publish(f"{cmd}/set_zero_type", '{"type": "absolute"}', qos=1,
                           retain=True).wait_for_publish(10)
        await until(lambda: nothing_retained(broker, f"{cmd}/+"))
    # A command sent after them all is answered first: nothing ran before it.
    result = await ask(f"{cmd}/read_settings", "{}")
    assert result["ok"] is True and result["answer"]["zero_type"] == "relative"
    assert ah.writes_heard == writes
    assert rec.on(f"{cmd}/save/result") == []


# ------------------------------------------------------------------ Home Assistant


@pytest.mark.anyio
async def test_discovery_configs_are_consistent_and_removed_with_their_sensor(
        tmp_path: Path) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    vg = sensor(WireProtocol.NATIVE, Series.VG, address=1, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah, vg]) as line:
        both: list[dict[str, Any]] = [{"name": "boom", "series": "AH"},
                                      {"name": "arm", "series": "VG", "address": 1}]
        cfg = config([bus("a", line.path, "native", both)], broker,
                     homeassistant_discovery=True, per_field_topics=True)

        async with running(cfg) as gateway:
            await until(lambda: all(gateway.cache.snapshot(n).seq >= 1
                                    for n in ("boom", "arm")))
            await until(lambda: written(gateway))
            kept = await asyncio.to_thread(retained, broker, "#")
        every = {m.topic: json.loads(m.payload) for m in kept
                 if m.topic.startswith("homeassistant/")}
        # the measured fields' entities (the others: the gateway's and diagnostics)
        configs = {t: c for t, c in every.items() if c.get("state_class") == "measurement"
                   and c["state_topic"].endswith("/ha")}
        others = {m.topic: m for m in kept}
        # the derived values have their per-field topics too
        assert {f"{BASE}/arm/tilt", f"{BASE}/boom/tilt_direction"} <= set(others)
        # every entity's template reads a topic the gateway really publishes
        for topic, c in every.items():
            assert c["state_topic"] in others, topic
        # One entity per measured field: AH all 16, VG all but the magnetometer.
        # And one per derived field (docs/alarms.md).
        fields = {"boom": set(FIELDS) | DERIVED,
                  "arm": {f for f in FIELDS if GROUP_OF[f] != "mag"} | DERIVED}
        want = {f"homeassistant/sensor/{GID}_{s}_{f}/config"
                for s, names in fields.items() for f in names}
        assert set(configs) == want
        assert len({c["unique_id"] for c in configs.values()}) == len(want)
        for topic, c in configs.items():
            for key in ("name", "unique_id", "state_topic", "value_template", "device",
                        "availability"):
                assert key in c, (topic, key)
            assert c["device"]["identifiers"] and c["device"]["name"]
            assert c.get("state_class") == "measurement"
            # The template points into the state JSON that is really published.
            group, member = c["value_template"].strip("{} ").split(".")[1:]
            published = state(others[c["state_topic"]])
            # (the vibration is null while the last second holds under ten samples)
            assert isinstance(published[group][member], float) or member == "vibration"
            for a in c["availability"]:
                if "value_template" in a:  # the reading's status: a JSON topic
                    assert state(others[a["topic"]])["status"] == "ok"
                else:
                    assert others[a["topic"]].text in ("online", "offline")
            unit = c.get("unit_of_measurement")
            field_name = topic.split("/")[2].split("_", 2)[2]
            assert unit == {"angles": "°", "accel": "g", "gyro": "°/s", "mag": "G",
                            "quaternion": None, "tilt": "°", "vibration": "g"}[
                GROUP_OF.get(field_name, field_name.removesuffix("_direction"))]

        # Restart with the AH sensor gone and per-field topics off: the AH's entities,
        # state, availability and values are removed, and the VG's values; the VG's
        # entities, state and availability stay.
        cfg["buses"][0]["sensors"] = [both[1]]
        cfg["mqtt"]["per_field_topics"] = False
        gone = {t for t in every if "_boom_" in t} | \
            {m.topic for m in kept if m.topic.startswith(f"{BASE}/boom/")} | \
            {f"{BASE}/arm/{f}" for f in fields["arm"]
             if f"{BASE}/arm/{f}" in others}  # (a vibration of no value is never sent)
        async with running(cfg) as gateway:
            mqtt = gateway.mqtt
            assert mqtt is not None
            await until(lambda: mqtt.sweep.cleared >= len(gone), timeout=20)
            await until(lambda: written(gateway))
            assert mqtt.sweep.cleared == len(gone)
            kept = await asyncio.to_thread(retained, broker, "#")
        left = {m.topic for m in kept if m.payload}
        assert left == {t for t in every if "_boom_" not in t} | {
            f"{BASE}/status", f"{BASE}/instance", f"{BASE}/diagnostics",
            f"imu/_clients/imu-gateway-{GID}",
            *(f"{BASE}/arm/{leaf}" for leaf in ("state", "availability", "settings", "ha",
                                                "alarm/communication"))}


# ------------------------------------------------------------------ the broker away


@pytest.mark.anyio
async def test_broker_restart_reconnects_and_republishes_and_queue_stays_bounded(
        tmp_path: Path) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=Motion.from_seed(5))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line:
        cfg = config([bus("a", line.path, "native",
                          [{"name": "boom", "series": "AH", "poll_hz": 0}])], broker,
                     queue_size=20, homeassistant_discovery=True)

        async with running(cfg) as gateway:
            mqtt = gateway.mqtt
            assert mqtt is not None
            await until(lambda: mqtt.connected)
            broker.stop()
            await until(lambda: not mqtt.connected)
            seq = gateway.cache.snapshot("boom").seq
            await until(lambda: gateway.cache.snapshot("boom").seq > seq + 60)
            assert len(mqtt.outbox) <= 20
            assert mqtt.stats()["dropped"] > 0
            broker.start()  # the same port; it remembers nothing
            await until(lambda: mqtt.connected and mqtt.stats()["connects"] == 2,
                        timeout=20)
            await until(lambda: written(gateway))
            kept = {m.topic: m for m in await asyncio.to_thread(retained, broker, "#")}
            assert kept[f"{BASE}/status"].text == "online"
            assert kept[f"{BASE}/boom/availability"].text == "online"
            assert state(kept[f"{BASE}/boom/state"])["seq"] > seq
            assert f"homeassistant/sensor/{GID}_boom_pitch/config" in kept



@pytest.mark.anyio
async def test_no_broker_the_gateway_runs_and_connects_when_one_appears(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, "imu_gateway.mqtt")
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    broker = Mosquitto(tmp_path)  # not started yet
    with simulated([ah]) as line:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])],
                     broker)

        async with running(cfg) as gateway:
            await until(lambda: gateway.cache.snapshot("boom").seq >= 3)
            await asyncio.sleep(2.0)  # several connection attempts
            with broker:
                assert gateway.mqtt is not None
                await until(lambda: gateway.mqtt is not None and gateway.mqtt.connected,
                            timeout=20)

    refused = [r for r in caplog.records if "cannot connect" in r.getMessage()]
    assert len(refused) == 1, [r.getMessage() for r in refused]  # once, not every retry
    assert "refused" in refused[0].getMessage().lower()
    assert any("connected to" in r.getMessage() for r in caplog.records)


# ------------------------------------------------------------------ the gateway process


def _run_gateway(tmp_path: Path, cfg: dict[str, Any]) -> subprocess.Popen[bytes]:
    path = tmp_path / "gateway.yaml"
    path.write_text(yaml.safe_dump(cfg))
    with (tmp_path / "gateway.log").open("wb") as log:
        return subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c", str(path)],
                                stdout=log, stderr=subprocess.STDOUT)


@pytest.mark.parametrize("how", ["killed", "interrupted"])
def test_the_broker_says_offline_when_the_gateway_goes(tmp_path: Path, how: str) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{BASE}/status", f"{BASE}/boom/availability") as rec:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])],
                     broker)
        gateway = _run_gateway(tmp_path, cfg)
        try:
            rec.wait(lambda: "online" in [m.text for m in rec.on(f"{BASE}/boom/availability")],
                     timeout=30)
            gateway.send_signal(signal.SIGKILL if how == "killed" else signal.SIGINT)
            code = gateway.wait(20)
        finally:
            if gateway.poll() is None:
                gateway.kill()
            gateway.wait()  # reaped, whatever happened: no process outlives its test
        rec.wait(lambda: rec.last(f"{BASE}/status") is not None
                 and rec.last(f"{BASE}/status").text == "offline")  # type: ignore[union-attr]
        if how == "interrupted":
            assert code == 0
            assert rec.last(f"{BASE}/boom/availability").text == "offline"  # type: ignore[union-attr]
        else:
            assert code == -signal.SIGKILL  # the last will spoke for it


@pytest.mark.parametrize("response_topic", ["x/#", "r/+/x", "t" * 65_000],
                         ids=["wildcard", "plus", "longest-possible"])
def test_a_bad_response_topic_gets_an_error_and_the_gateway_goes_on(
        tmp_path: Path, response_topic: str) -> None:
    """An MQTT 5 command whose response topic the gateway cannot (or will not) publish
    to: an error result on the default result topic, and states keep flowing.  (An
    MQTT property is at most 65,535 bytes: 65,000 is about the longest a client can
    send.)"""
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    cmd = f"{BASE}/boom/cmd/read_settings"
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{cmd}/result", f"{BASE}/boom/state",
                      version=paho.MQTTv5) as rec:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])],
                     broker, allow_commands=True, protocol="5", retain=False)
        gateway = _run_gateway(tmp_path, cfg)
        try:
            rec.wait(lambda: rec.on(f"{BASE}/boom/state"), timeout=30)
            props = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
            props.ResponseTopic = response_topic
            props.CorrelationData = b"c-1"
            rec.client.publish(cmd, b"{}", qos=1, properties=props)
            rec.wait(lambda: rec.on(f"{cmd}/result"), timeout=30)
            result = state(rec.on(f"{cmd}/result")[0])
            assert result["ok"] is False and result["kind"] == "bad_arguments"
            assert "response topic" in result["error"]
            states = len(rec.on(f"{BASE}/boom/state"))
            rec.wait(lambda: len(rec.on(f"{BASE}/boom/state")) > states + 10, timeout=30)
            assert gateway.poll() is None
        finally:
            code = interrupt(gateway, 20)
    assert code == 0
    log_text = (tmp_path / "gateway.log").read_text()
    assert "Traceback" not in log_text and "failed (" not in log_text, log_text[-2000:]


@pytest.mark.anyio
async def test_a_message_paho_cannot_send_is_dropped_and_the_queue_goes_on(
        tmp_path: Path) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{BASE}/boom/state") as rec:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])],
                     broker, retain=False)

        async with running(cfg) as gateway:
            mqtt = gateway.mqtt
            assert mqtt is not None
            await until(lambda: mqtt.connected and bool(rec.on(f"{BASE}/boom/state")))
            # first in the queue that never drops: it must not hold the rest up
            mqtt._send_control(Message("bad/#", b"x", 1, False))
            before = len(rec.on(f"{BASE}/boom/state"))
            await until(lambda: len(rec.on(f"{BASE}/boom/state")) > before + 5)
            stats = mqtt.stats()
            assert stats["undeliverable"] == 1 and stats["connected"] is True



@pytest.mark.anyio
async def test_a_failed_mqtt_client_is_restarted_and_the_rest_goes_on(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """A fault inside the MQTT front end (here: its cache listener raises once) is
    logged, counted, and that front end alone restarts; the bus goes on."""
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    failures = iter([True])
    original = StateDesk._publish_state

    def flaky(self: StateDesk, snap: Any) -> None:
        # once connected (on a busy machine the first readings may come before the
        # connect has: the test is of a client that has said "online")
        if self.connected() and next(failures, False):
            raise RuntimeError("boom")
        original(self, snap)

    monkeypatch.setattr(StateDesk, "_publish_state", flaky)
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{BASE}/boom/state", f"{BASE}/status") as rec:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])],
                     broker, retain=False)

        async with running(cfg) as gateway:
            await until(lambda: gateway.supervisor.restarts["mqtt"] == 1)
            seq = gateway.cache.snapshot("boom").seq
            before = len(rec.on(f"{BASE}/boom/state"))
            await until(lambda: len(rec.on(f"{BASE}/boom/state")) > before + 5)
            assert gateway.cache.snapshot("boom").seq > seq
            assert gateway.frontend_stats()["mqtt"]["restarts"] == 1

    failed = [r.getMessage() for r in caplog.records if "mqtt failed" in r.getMessage()]
    assert len(failed) == 1 and "RuntimeError: boom" in failed[0]
    # the restart said so, then the stop at the end (the first "online" may never have
    # left: a newer message for the same retained topic replaces one still waiting)
    statuses = [m.text for m in rec.on(f"{BASE}/status")]
    assert statuses[-3:] == ["offline", "online", "offline"], statuses


# ------------------------------------------------------------------ TLS and passwords


def _secure(tls: Tls) -> dict[str, Any]:
    return {"username": "gateway", "password": "${MQTT_PASSWORD}", "ca_file": str(tls.ca),
            "certfile": str(tls.client_cert), "keyfile": str(tls.client_key)}


USERS = {"gateway": "s3cret", "dashboard": "look"}


@pytest.mark.anyio
async def test_tls_with_a_test_ca_client_certificate_and_password(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, "imu_gateway.mqtt")
    tls = make_tls(tmp_path / "pki")
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path, tls=tls, users=USERS) as broker, simulated([ah]) as line, \
            recording(broker, "imu/#", username="dashboard", password="look") as rec:
        buses = [bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])]

        async with running(config(buses, broker, **_secure(tls)),
                           env={"MQTT_PASSWORD": "s3cret"}):
            await until(lambda: bool(rec.on(f"{BASE}/boom/state")))
        # A wrong password: the broker's reason, once.
        async with running(config(buses, broker, **_secure(tls)),
                           env={"MQTT_PASSWORD": "wrong"}) as gateway:
            await until(lambda: any("refused" in r.getMessage() for r in caplog.records))
            assert gateway.mqtt is not None and not gateway.mqtt.connected

        assert state(rec.on(f"{BASE}/boom/state")[-1])["status"] == "ok"
        refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
        assert len(refused) == 1 and "not authori" in refused[0].lower(), refused


# paho 2.2 leaves the socket of a failed TLS handshake to its finaliser
# (``Client._ssl_wrap_socket``), which warns: that one warning is expected here.
@pytest.mark.filterwarnings(
    "ignore:Exception ignored in. <ssl.SSLSocket:pytest.PytestUnraisableExceptionWarning")
@pytest.mark.anyio
async def test_tls_with_a_ca_that_did_not_sign_the_broker_says_why(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, "imu_gateway.mqtt")
    tls, other = make_tls(tmp_path / "pki"), make_tls(tmp_path / "other-pki")
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path, tls=tls, users=USERS) as broker, simulated([ah]) as line:
        buses = [bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])]
        cfg = config(buses, broker, **{**_secure(tls), "ca_file": str(other.ca)})

        async with running(cfg, env={"MQTT_PASSWORD": "s3cret"}) as gateway:
            await until(lambda: any("certificate" in r.getMessage()
                                    for r in caplog.records))
            await until(lambda: gateway.cache.snapshot("boom").seq >= 1)  # runs on

        problems = [r.getMessage() for r in caplog.records if "certificate" in r.getMessage()]
        assert "certificate verify failed" in problems[0]
    # That socket is held by a reference cycle through the error's traceback (the
    # probe keeps the error it reports): collected now, while this test's filter holds.
    gc.collect()


# ------------------------------------------------------------------ throttling


@pytest.mark.anyio
async def test_min_interval_deadband_and_per_field_topics(tmp_path: Path) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{BASE}/#") as rec:
        buses = [bus("a", line.path, "native",
                     [{"name": "boom", "series": "AH", "poll_hz": 0}])]

        # min_interval: at most one message per 400 ms, however fast the polls.
        async with running(config(buses, broker, min_interval_ms=400,
                                  per_field_topics=True)) as gateway:
            await until(lambda: bool(rec.on(f"{BASE}/boom/state")))
            first_seq = gateway.cache.snapshot("boom").seq
            start = asyncio.get_running_loop().time()
            rec.clear()
            await asyncio.sleep(2.0)
            elapsed = asyncio.get_running_loop().time() - start
            polled = gateway.cache.snapshot("boom").seq - first_seq
            sent = len(rec.on(f"{BASE}/boom/state"))
            assert polled > 3 * sent  # the polls outnumber the messages
            assert 1 <= sent <= elapsed / 0.4 + 1
            # per_field_topics: plain numbers equal to the state JSON's.
            last = fields_of(state(rec.on(f"{BASE}/boom/state")[-1]))
            await until(lambda: bool(rec.on(f"{BASE}/boom/q3")))
            for name in FIELDS:
                assert float(rec.last(f"{BASE}/boom/{name}").text) == last[name]  # type: ignore[union-attr]

        # deadband: a still sensor sends one message; a move past the band, another.
        rec.clear()
        async with running(config(buses, broker, deadband={"angles": 1.0})) as gateway:
            await until(lambda: bool(rec.on(f"{BASE}/boom/state")))
            seq = gateway.cache.snapshot("boom").seq
            await until(lambda: gateway.cache.snapshot("boom").seq > seq + 20)
            assert value_messages(rec.on(f"{BASE}/boom/state")) == 1
            a = READING.angles
            assert a is not None
            ah.source = hold(_replace_angles(READING, Angles(a.pitch + 0.5, a.roll, a.yaw)))
            seq = gateway.cache.snapshot("boom").seq
            await until(lambda: gateway.cache.snapshot("boom").seq > seq + 20)
            assert value_messages(rec.on(f"{BASE}/boom/state")) == 1  # within the band
            ah.source = hold(_replace_angles(READING, Angles(a.pitch + 5, a.roll, a.yaw)))
            await until(lambda: value_messages(rec.on(f"{BASE}/boom/state")) == 2)
            moved = state(rec.on(f"{BASE}/boom/state")[-1])["angles"]["pitch"]
            assert abs(moved - (a.pitch + 5)) < 0.01



def value_messages(messages: list[Any]) -> int:
    """State messages sent for a value, not for a change of status: a status change is
    always published (a busy machine may make a still sensor stale for a moment)."""
    statuses = [str(state(m)["status"]) for m in messages]
    return len(statuses) - sum(a != b for a, b in itertools.pairwise(statuses))


def _replace_angles(reading: Any, angles: Angles) -> Any:
    from dataclasses import replace
    return replace(reading, angles=angles)


@pytest.mark.anyio
async def test_plain_mqtt_to_a_tls_port_says_so(tmp_path: Path,
                                          caplog: pytest.LogCaptureFixture) -> None:
    """A TLS listener closes a plain connection (or, elsewhere, waits for a TLS hello
    and says nothing): the gateway says so once, and why it might be."""
    caplog.set_level(logging.WARNING, "imu_gateway.mqtt")
    tls = make_tls(tmp_path / "pki")
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path, tls=tls) as broker, simulated([ah]) as line:
        plain = broker.url.replace("mqtts://", "mqtt://")
        cfg = {"gateway_id": GID, "buses": [bus("a", line.path, "native",
                                                [{"name": "boom", "series": "AH"}])],
               "mqtt": {"url": plain}}

        async with running(cfg) as gateway:
            await until(lambda: any("use mqtts://" in r.getMessage()
                                    for r in caplog.records), timeout=30)
            assert gateway.mqtt is not None and not gateway.mqtt.connected
            await until(lambda: gateway.cache.snapshot("boom").seq >= 1)  # runs on

    said = [r.getMessage() for r in caplog.records if "mqtts://" in r.getMessage()]
    assert len(said) == 1, said  # once, not at every retry


@pytest.mark.anyio
async def test_a_server_that_never_answers_connect_is_given_up_on(
        caplog: pytest.LogCaptureFixture) -> None:
    """Not a broker at all (or a TLS port that waits for a hello): a TCP server that
    accepts and says nothing.  Each attempt ends after CONNACK_TIMEOUT, said once."""
    caplog.set_level(logging.WARNING, "imu_gateway.mqtt")
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with simulated([ah]) as line:
        accepted: list[asyncio.StreamWriter] = []
        silent = await asyncio.start_server(lambda r, w: accepted.append(w),
                                            "127.0.0.1", 0)
        port = silent.sockets[0].getsockname()[1]
        cfg = {"gateway_id": GID, "buses": [bus("a", line.path, "native",
                                                [{"name": "boom", "series": "AH"}])],
               "mqtt": {"url": f"mqtt://127.0.0.1:{port}"}}
        async with silent, running(cfg) as gateway:
            await until(lambda: any("no answer" in r.getMessage()
                                    for r in caplog.records), timeout=30)
            assert gateway.mqtt is not None and not gateway.mqtt.connected
        for writer in accepted:
            writer.close()
            await writer.wait_closed()

    said = [r.getMessage() for r in caplog.records if "no answer" in r.getMessage()]
    assert len(said) == 1 and "within 5 s" in said[0] and "mqtts://" in said[0]


@pytest.mark.anyio
async def test_twenty_sensors_all_discovery_configs_and_availabilities_arrive(
        tmp_path: Path) -> None:
    """384 discovery configs and 20 availabilities at one connect: more than paho's
    own queue would take at once; none may be lost."""
    sims = [sensor(WireProtocol.NATIVE, Series.AH, address=a, source=hold(READING))
            for a in range(20)]
    with Mosquitto(tmp_path) as broker, simulated(sims) as line:
        cfg = config([bus("a", line.path, "native",
                          [{"name": f"s{a}", "series": "AH", "address": a, "poll_hz": 2}
                           for a in range(20)])], broker, homeassistant_discovery=True)

        async with running(cfg) as gateway:
            await until(lambda: all(s.seq >= 1 for s in gateway.cache.snapshots()),
                        timeout=30)
            await until(lambda: written(gateway))
            kept = await asyncio.to_thread(retained, broker, "#")
            made = set(gateway.mqtt.discovery) if gateway.mqtt else set()
        topics = {m.topic for m in kept}
        # every config made arrives: 16 fields and 3 diagnostics a sensor, the gateway's
        assert {t for t in topics if t.startswith("homeassistant/")} == made
        assert len([t for t in made if "/diag_" not in t and "_s" in t]) >= 20 * 16
        assert {f"{BASE}/s{a}/availability" for a in range(20)} <= topics



@pytest.mark.anyio
async def test_a_connection_that_worked_resets_the_reconnect_back_off(tmp_path: Path) -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line:
        cfg = config([bus("a", line.path, "native", [{"name": "boom", "series": "AH"}])],
                     broker)

        async with running(cfg) as gateway:
            mqtt = gateway.mqtt
            assert mqtt is not None
            for restart in range(1, 6):
                await until(lambda: mqtt.connected)
                broker.stop()
                await until(lambda: not mqtt.connected)
                broker.start()

                def reconnected(r: int = restart) -> bool:
                    return mqtt.counters.connects == r + 1

                # 0.5 s each time; without the reset the fifth would wait 8 s
                await until(reconnected, timeout=4)

