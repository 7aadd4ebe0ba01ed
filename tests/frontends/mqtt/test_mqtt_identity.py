"""One gateway per gateway_id (and per client id) on a broker: the second says so and
stays away, rather than take the first's session or overwrite its retained messages."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import pytest
from support.broker import Mosquitto, recording
from support.harness import running, until

from imu_gateway.frontends.mqtt import identity as mqtt_identity
from imu_gateway.frontends.mqtt.identity import Claim, live_rival
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

MINE = Claim("a" * 32, "box1", 100, 1000.0, "gw", "imu-gateway-gw")
BOX2 = Claim("b" * 32, "box2", 200, 900.0, "gw", "imu-gateway-gw")
BOX1 = Claim("b" * 32, "box1", 200, 900.0, "gw", "imu-gateway-gw")


@pytest.mark.parametrize(("status", "theirs", "alive", "rival"), [
    ("online", BOX2, False, True),  # another box: live
    ("offline", BOX2, True, False),  # its will said so
    ("online", None, True, False),  # no claim: an empty or a malformed one
    ("online", MINE, True, False),  # its own
    ("online", BOX1, False, False),  # a crashed predecessor
    ("online", BOX1, True, True),  # a second one here
])
def test_a_rival_is_another_live_gateway(status: str, theirs: Claim | None, alive: bool,
                                         rival: bool) -> None:
    assert (live_rival(MINE, status, theirs, lambda pid: alive) is not None) is rival


def test_a_claim_survives_its_payload_and_nonsense_is_nobodys() -> None:
    assert Claim.parse(MINE.payload()) == MINE
    for junk in (b"", b"{", b"[]", b'{"instance": "x"}', b"\xff"):
        assert Claim.parse(junk) is None
    # values anyone with publish rights could write, which once ended the front end
    # (OverflowError in the parse, in os.kill, in the time shown)
    good = json.loads(MINE.payload())
    for field, value in (("pid", 1e400), ("pid", 10**30), ("pid", -1), ("pid", 0),
                         ("started", float("nan")), ("started", 1e20),
                         ("started", float("inf")), ("started", -5)):
        payload = json.dumps({**good, field: value}).encode()
        assert Claim.parse(payload) is None, (field, value)
    assert Claim.parse(b'{"instance": "x", "host": "h", "pid": Infinity, "started": 1, '
                       b'"gateway_id": "g", "client_id": "c"}') is None
    assert MINE.first(Claim("b" * 32, "box2", 1, 1000.5, "gw", "x"))


def _gateway(line: str, broker: Mosquitto, gid: str, **mqtt: Any) -> dict[str, Any]:
    return {"gateway_id": gid,
            "buses": [{"name": "a", "port": line, "baudrate": 115200, "protocol": "native",
                       "sensors": [{"name": "ah", "series": "AH", "poll_hz": 10}]}],
            "mqtt": {"url": broker.url, **mqtt}}


def _line() -> Any:
    return simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)])


@pytest.mark.anyio
async def test_a_second_gateway_with_the_same_id_stays_away_until_the_first_goes(
        tmp_path: Path, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mqtt_identity, "RIVAL_WAIT", 0.5)
    caplog.set_level(logging.ERROR, "imu_gateway.mqtt")
    with Mosquitto(tmp_path) as broker, _line() as one, _line() as two, \
            recording(broker, "imu/gw/#") as rec:
        async with running(_gateway(one.path, broker, "gw")) as first:
            assert first.mqtt is not None
            await until(lambda: bool(rec.on("imu/gw/ah/state")))
            async with running(_gateway(two.path, broker, "gw")) as second:
                assert second.mqtt is not None
                await until(lambda: "is in use on" in caplog.text)
                assert "host " in caplog.text and "give each gateway its own" in \
                    caplog.text.lower()
                # it looked again and again, and never connected: the first's session
                # and its retained status are untouched
                tries = caplog.text.count("is in use on")
                await until(lambda: second.mqtt is not None and
                            second.mqtt.identity.held_off is False and
                            first.mqtt is not None and first.mqtt.counters.connects == 1)
                assert tries == 1  # reported once
                assert second.mqtt.counters.connects == 0
                status = rec.last("imu/gw/status")
                assert status is not None and status.text == "online"
                claim = Claim.parse(rec.last("imu/gw/instance").payload)  # type: ignore[union-attr]
                assert claim == first.mqtt.identity.claim
            # the first goes; ...
            rec.clear()
        # ... then a third with that id is welcome
        async with running(_gateway(two.path, broker, "gw")) as third:
            await until(lambda: third.mqtt is not None and third.mqtt.counters.connects == 1)
            await until(lambda: rec.last("imu/gw/status") is not None and
                        rec.last("imu/gw/status").text == "online")  # type: ignore[union-attr]


@pytest.mark.anyio
@pytest.mark.parametrize("protocol", ["3.1.1", "5"])
async def test_a_client_id_in_use_by_another_gateway_is_not_taken(
        protocol: str, tmp_path: Path, caplog: pytest.LogCaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Two gateways of different ids, one client id: the broker would hand the session
    back and forth at every reconnect.  The second finds the first's claim, sees it is
    running, and stays away."""
    monkeypatch.setattr(mqtt_identity, "RIVAL_WAIT", 0.5)
    caplog.set_level(logging.ERROR, "imu_gateway.mqtt")
    with Mosquitto(tmp_path) as broker, _line() as one, _line() as two, \
            recording(broker, "imu/+/ah/state") as rec:
        same = {"client_id": "plant-gateway", "protocol": protocol}
        async with running(_gateway(one.path, broker, "north", **same)) as north:
            await until(lambda: bool(rec.on("imu/north/ah/state")))
            async with running(_gateway(two.path, broker, "south", **same)) as south:
                await until(lambda: "the client id 'plant-gateway' is in use" in caplog.text)
                mark = len(rec.on("imu/north/ah/state"))
                await until(lambda: len(rec.on("imu/north/ah/state")) >= mark + 10)
                assert north.mqtt is not None and north.mqtt.counters.connects == 1
                assert south.mqtt is not None and south.mqtt.counters.connects == 0
                assert not rec.on("imu/south/ah/state")
