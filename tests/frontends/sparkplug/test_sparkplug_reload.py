"""A reload that changes the sensors is a rebirth of the edge node on the same MQTT
session (docs/sparkplug.md, "A reload"), against a real mosquitto, every payload read
by Eclipse Tahu's decoder: a DDEATH for the device removed, then the NBIRTH (seq 0,
the same bdSeq) and a DBIRTH for each device of the new set; one CONNECT at the
broker, no NDEATH."""

from __future__ import annotations

import copy
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from support.broker import Mosquitto, Received, Recorder, recording
from support.harness import running, until
from support.tahu import Tahu

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GROUP, NODE, SP = "plant", "gw1", "spBv1.0"
CLIENT_ID = f"imu-gateway-{NODE}-sparkplug"
READING = Motion.from_seed(5).sample(3.0)


@pytest.fixture(scope="module")
def tahu() -> Iterator[Tahu]:
    codec = Tahu()
    yield codec
    codec.close()


def _config(line: str, broker: Mosquitto) -> dict[str, Any]:
    return {"gateway_id": NODE,
            "buses": [{"name": "a", "port": line, "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "poll_hz": 5},
                                   {"name": "arm", "series": "AH", "address": 1,
                                    "poll_hz": 5}]}],
            "mqtt": {"url": broker.url,
                     "sparkplug": {"group_id": GROUP, "plain_topics": False}}}


def _node_messages(rec: Recorder) -> list[Received]:
    return [m for m in list(rec.messages) if m.topic.startswith(f"{SP}/{GROUP}/")]


def _kind(m: Received) -> str:
    device = m.topic.split("/")[4:]
    return "/".join([m.topic.split("/")[2], *device])


def _connects(broker: Mosquitto) -> int:
    return len(re.findall(rf"New client connected from \S+ as {re.escape(CLIENT_ID)} \(",
                          broker.log.read_text()))


def _metric(payload: dict[str, Any], name: str) -> dict[str, Any]:
    found: list[dict[str, Any]] = [m for m in payload["metrics"] if m.get("name") == name]
    assert len(found) == 1, (name, found)
    return found[0]


@pytest.mark.anyio
async def test_a_reload_is_a_rebirth_on_the_same_session(tmp_path: Path, tahu: Tahu) -> None:
    sims = [make_sensor(WireProtocol.NATIVE, Series.AH, address, baud=115200,
                        source=hold(READING)) for address in (0, 1, 2)]
    with Mosquitto(tmp_path) as broker, simulated(sims) as line, \
            recording(broker, f"{SP}/#") as rec:
        first = _config(line.path, broker)
        async with running(first) as gw:
            births = ("NBIRTH", "DBIRTH/boom", "DBIRTH/arm")
            await until(lambda: set(births) <= {_kind(m) for m in _node_messages(rec)}, 20)
            mark = len(_node_messages(rec))
            second = copy.deepcopy(first)
            second["buses"][0]["sensors"][1] = {"name": "mast", "series": "AH",
                                                "address": 2, "poll_hz": 5}
            await gw.reloader.put(second, dry_run=False)
            await until(lambda: "DBIRTH/mast" in
                        [_kind(m) for m in _node_messages(rec)[mark:]], 20)
        messages = _node_messages(rec)
        connects = _connects(broker)
    before = [(_kind(m), tahu.decode(m.payload)) for m in messages[:mark]]
    after = [(_kind(m), tahu.decode(m.payload)) for m in messages[mark:]]
    kinds = [k for k, _ in after]
    # arm's death, then the births of the new set; no NDEATH until the gateway stopped
    assert kinds[kinds.index("DDEATH/arm") + 1] == "NBIRTH", kinds
    rebirth = kinds.index("NBIRTH")
    assert "NDEATH" not in kinds[:-1], kinds  # (the last: the gateway's stop, if heard)
    assert "DBIRTH/boom" in kinds[rebirth:] and "DBIRTH/mast" in kinds[rebirth:]
    assert not [k for k in kinds[rebirth:] if k.endswith("/arm")]
    # seq: the DDEATH goes on from the last one; the NBIRTH starts again at 0
    seqs = [p["seq"] for k, p in [*before, *after][:mark + rebirth]]
    assert seqs == [i % 256 for i in range(len(seqs))]
    assert after[rebirth][1]["seq"] == 0 and after[rebirth + 1][1]["seq"] == 1
    # the same session: the same bdSeq, one CONNECT at the broker
    bdseq = _metric(before[0][1], "bdSeq")["value"]
    assert _metric(after[rebirth][1], "bdSeq")["value"] == bdseq
    assert connects == 1
    # boom keeps its aliases; mast's are new, none shared with another metric
    def aliases(kind: str, births: list[tuple[str, dict[str, Any]]]) -> dict[str, int]:
        payload = next(p for k, p in births if k == kind)
        return {m["name"]: m["alias"] for m in payload["metrics"]}

    assert aliases("DBIRTH/boom", after) == aliases("DBIRTH/boom", before)
    numbers = [*aliases("NBIRTH", after).values(), *aliases("DBIRTH/boom", after).values(),
               *aliases("DBIRTH/mast", after).values()]
    assert len(numbers) == len(set(numbers))
    assert not set(aliases("DBIRTH/mast", after).values()) & \
        set(aliases("DBIRTH/arm", before).values())
