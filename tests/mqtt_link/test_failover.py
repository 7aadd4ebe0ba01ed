"""Broker failover: ``mqtt.url`` lists a cluster's nodes.  When the node the gateway is
on goes, it moves to the next and republishes everything retained there; its last
will works on whichever node it is on.  The order and waits (``Failover``) are sans-IO
and tested in plain time; the moves against two real mosquitto brokers."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from support.broker import Gate, Mosquitto, Recorder, recording
from support.harness import running, until

from imu_gateway.app import Gateway
from imu_gateway.config import Broker
from imu_gateway.model import Series, WireProtocol
from imu_gateway.mqtt_link import probe
from imu_gateway.mqtt_link.failover import RECONNECT_MAX, RECONNECT_MIN, Failover
from imu_gateway.simulator import make_sensor, simulated

GID = "gw"
BASE = f"imu/{GID}"
NODES = (Broker("n1", 1883), Broker("n2", 1883), Broker("n3", 1883))


def test_a_failed_try_goes_on_to_the_next_node_at_once_and_waits_after_a_round() -> None:
    f = Failover(NODES)
    waits = []
    for _ in range(9):  # three whole rounds fail
        waits.append((str(f.current), f.ended(worked=False)))
    assert waits == [("n1:1883", 0.0), ("n2:1883", 0.0), ("n3:1883", RECONNECT_MIN),
                     ("n1:1883", 0.0), ("n2:1883", 0.0), ("n3:1883", 2 * RECONNECT_MIN),
                     ("n1:1883", 0.0), ("n2:1883", 0.0), ("n3:1883", 4 * RECONNECT_MIN)]


def test_a_lost_connection_moves_to_the_next_node_and_starts_the_back_off_again() -> None:
    f = Failover(NODES)
    for _ in range(30):
        f.ended(worked=False)
    assert f.delay == RECONNECT_MAX
    at = f.current
    assert f.ended(worked=True) == RECONNECT_MIN  # the one it was on may be the one down
    assert f.current != at and f.delay == RECONNECT_MIN and f.failures == 0


def test_one_broker_is_the_plain_back_off() -> None:
    f = Failover(NODES[:1])
    assert [f.ended(worked=False) for _ in range(4)] == \
        [RECONNECT_MIN, 2 * RECONNECT_MIN, 4 * RECONNECT_MIN, 8 * RECONNECT_MIN]
    assert f.current == NODES[0]


def _config(line: str, urls: list[str]) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": line, "baudrate": 115200, "protocol": "native",
                       "sensors": [{"name": "ah", "series": "AH", "poll_hz": 20}]}],
            "mqtt": {"url": urls, "homeassistant_discovery": True}}


@pytest.mark.anyio
async def test_the_gateway_moves_to_the_next_node_and_republishes_there(
        tmp_path: Path) -> None:
    (tmp_path / "n1").mkdir()
    (tmp_path / "n2").mkdir()
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path / "n1") as n1, Mosquitto(tmp_path / "n2") as n2, \
            simulated([ah]) as line:
        async with Gate(n2.port) as gate:
            # n2 through a gate the test can cut: the broker then sees the gateway's
            # connection drop, as when the gateway's machine loses its network
            urls = [n1.url, f"mqtt://127.0.0.1:{gate.port}"]
            with recording(n1, f"{BASE}/status") as on_n1, recording(n2, "#") as on_n2:
                async with running(_config(line.path, urls)) as gw:
                    await until(lambda: [m.text for m in on_n1.on(f"{BASE}/status")]
                                == ["online"])
                    lost_at = time.monotonic()
                    n1.stop()
                    # on n2: the gateway's status, availability, discovery and state
                    await until(lambda: bool(on_n2.on(f"{BASE}/ah/state")), 15)
                    moved = on_n2.on(f"{BASE}/status")[0]
                    assert moved.text == "online" and moved.at - lost_at < 10
                    await until(lambda: [m.text for m in on_n2.on(f"{BASE}/ah/availability")]
                                == ["online"])
                    await until(lambda: any(m.topic.startswith("homeassistant/")
                                            for m in list(on_n2.messages)))
                    assert gw.mqtt is not None and gw.mqtt.counters.connects == 2
                    # a subscriber that comes now gets the retained status from n2
                    with recording(n2, f"{BASE}/status") as late:
                        await until(lambda: bool(late.on(f"{BASE}/status")))
                        assert late.on(f"{BASE}/status")[0].retain
                        assert late.on(f"{BASE}/status")[0].text == "online"
                    # the will, on n2: the connection drops without a DISCONNECT
                    on_n2.clear()
                    gate.cut()
                    await until(lambda: [m.text for m in on_n2.on(f"{BASE}/status")]
                                == ["offline"], 15)


Serve = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


@contextlib.asynccontextmanager
async def _behind(serve: Serve, tmp_path: Path) -> AsyncIterator[tuple[Gateway, Recorder]]:
    """A gateway whose broker list starts with a TCP server that is no broker
    (``serve`` takes each connection), then a real mosquitto; and a recorder of its
    status on the mosquitto."""
    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path) as n2, simulated([ah]) as line, \
            recording(n2, f"{BASE}/status") as on_n2:
        async with server, running(_config(line.path, [f"mqtt://127.0.0.1:{port}",
                                                       n2.url])) as gw:
            yield gw, on_n2


@pytest.mark.anyio
async def test_a_node_that_never_answers_costs_one_try_not_two(tmp_path: Path) -> None:
    """A recovering cluster node may accept a connection and say nothing.  The identity
    probe's connect is then that node's try: the gateway goes on to the next node
    without a connection of its own (and a second wait) to the silent one.  (The
    probes there are several: one more every 0.5 s while none answers.)"""
    accepted: list[asyncio.StreamWriter] = []
    connects: list[bytes] = []  # each CONNECT packet the silent node got

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        accepted.append(writer)
        connects.append(await reader.read(1024))

    async with _behind(hold, tmp_path) as (gw, on_n2):
        await until(lambda: [m.text for m in on_n2.on(f"{BASE}/status")] == ["online"])
        assert gw.mqtt is not None and gw.mqtt.connected
        await until(lambda: len(connects) == len(accepted))
        assert connects and all(b"-probe-" in packet for packet in connects), connects
    for writer in accepted:
        writer.close()
        await writer.wait_closed()


@pytest.mark.anyio
async def test_a_late_will_is_answered_with_online_again(tmp_path: Path) -> None:
    """A cluster can publish the will of a connection it lost (its node died) after
    the gateway said online on another node: the retained status would say offline
    while the gateway runs.  Heard live, the gateway says online again."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{BASE}/status") as rec:
        async with running(_config(line.path, [broker.url])) as gw:
            await until(lambda: [m.text for m in rec.on(f"{BASE}/status")] == ["online"])
            # the will, as the broker would publish it: retained, from elsewhere
            rec.client.publish(f"{BASE}/status", b"offline", qos=1, retain=True)
            await until(lambda: [m.text for m in rec.on(f"{BASE}/status")]
                        == ["online", "offline", "online"])
            assert gw.mqtt is not None and gw.mqtt.connected
            with recording(broker, f"{BASE}/status") as late:
                await until(lambda: bool(late.on(f"{BASE}/status")))
                assert [m.text for m in late.on(f"{BASE}/status")] == ["online"]
        # its own offline at a stop is not answered
        assert [m.text for m in rec.on(f"{BASE}/status")][-1] == "offline"


@pytest.mark.anyio
async def test_a_reconnect_takes_the_first_node_that_answers(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """After a loss, a node that holds the probe unanswered (a cluster node still
    electing) gets another probe beside it on the next node every 0.5 s; the gateway
    connects to the first that answers.  The probe's own limit is made a minute here,
    so a gateway that waited for the silent node would not be back within the test."""
    monkeypatch.setattr(probe, "PROBE_TIMEOUT", 60.0)
    connects: list[bytes] = []

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        connects.append(await reader.read(1024))
        await reader.read()  # until the gateway closes it
        writer.close()

    silent = await asyncio.start_server(hold, "127.0.0.1", 0)
    port = silent.sockets[0].getsockname()[1]
    (tmp_path / "n1").mkdir()
    (tmp_path / "n3").mkdir()
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path / "n1") as n1, Mosquitto(tmp_path / "n3") as n3, \
            simulated([ah]) as line, recording(n3, f"{BASE}/status") as on_n3:
        urls = [n1.url, f"mqtt://127.0.0.1:{port}", n3.url]
        async with silent, running(_config(line.path, urls)) as gw:
            await until(lambda: gw.mqtt is not None and gw.mqtt.connected)
            n1.stop()
            # (its status guard may say online again later: the silent node does not
            # answer its read-back either)
            await until(lambda: "online" in [m.text for m in on_n3.on(f"{BASE}/status")],
                        30)
            assert gw.mqtt is not None and gw.mqtt.failover.current.port == n3.port
            assert connects and all(b"-probe-" in packet for packet in connects), connects


@pytest.mark.anyio
async def test_a_reconnect_publishes_only_what_the_broker_does_not_serve(
        tmp_path: Path) -> None:
    """Back on a broker that kept this gateway's retained messages (the same broker, or
    a node of the same cluster), the gateway publishes again only those it does not
    serve as they are (and the status, always, on the broker it was last on): here
    the status, which the will made ``offline``; not the claim, the availability or
    the discovery configs."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path) as n1, simulated([ah]) as line:
        async with Gate(n1.port) as gate:
            # (QoS 0: mosquitto then passes the messages on in the order they came)
            with recording(n1, f"{BASE}/#", "homeassistant/#", qos=0) as rec:
                urls = [f"mqtt://127.0.0.1:{gate.port}"]
                async with running(_config(line.path, urls)) as gw:
                    await until(lambda: any(m.topic.startswith("homeassistant/")
                                            for m in list(rec.messages)))
                    # (online: the first connect may come before the sensor's first
                    # answer, and say offline first)
                    await until(lambda: [m.text for m in rec.on(f"{BASE}/ah/availability")
                                         ][-1:] == ["online"])
                    rec.clear()
                    gate.cut()  # the broker sees the connection drop: the will
                    await until(lambda: bool(rec.on(f"{BASE}/status")), 15)
                    gate.shut = False
                    await until(lambda: [m.text for m in rec.on(f"{BASE}/status")]
                                == ["offline", "online"], 15)
                    assert gw.mqtt is not None and gw.mqtt.counters.connects == 2
                    await until(lambda: bool(rec.on(f"{BASE}/ah/state")))
                    again = {m.topic for m in list(rec.messages) if m.topic not in
                             (f"{BASE}/status", f"{BASE}/ah/state")}
                    assert not any(t.startswith("homeassistant/") for t in again), again
                    assert f"{BASE}/ah/availability" not in again
                    assert f"{BASE}/instance" not in again


@pytest.mark.anyio
async def test_back_on_a_broker_that_missed_the_loss_the_status_is_said_again(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The connection is lost on the gateway's side only: the broker still takes it for
    alive, serves the status ``online``, and publishes the old connection's will as
    the new one takes the session over.  The gateway says ``online`` after that, on
    the broker it was last on, though the probe found it served so."""
    caplog.set_level(logging.WARNING, "imu_gateway.mqtt")
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path) as n1, simulated([ah]) as line:
        async with Gate(n1.port) as gate:
            with recording(n1, f"{BASE}/status", qos=0) as rec:
                async with running(_config(line.path, [f"mqtt://127.0.0.1:{gate.port}"])) \
                        as gw:
                    await until(lambda: [m.text for m in rec.on(f"{BASE}/status")]
                                == ["online"])
                    gate.cut(client_side_only=True)
                    await until(lambda: gw.mqtt is not None and not gw.mqtt.connected)
                    gate.shut = False
                    # the will, at the takeover, then online from the new connection
                    await until(lambda: [m.text for m in rec.on(f"{BASE}/status")]
                                == ["online", "offline", "online"], 15)
                    assert gw.mqtt is not None and gw.mqtt.connected
    guarded = [r.getMessage() for r in caplog.records if "not online" in r.getMessage()]
    assert not guarded, guarded  # said at the connect, not mended by the guard later


@pytest.mark.anyio
async def test_a_node_that_closes_at_once_gets_one_probe_not_a_storm(
        tmp_path: Path) -> None:
    """A node that closes each connection at once (a TLS port spoken to in plain MQTT,
    a broker at its connection limit): the probe fails, and the gateway goes on to the
    next node; no probe after probe while its time lasts."""
    accepted: list[int] = []

    async def close(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        accepted.append(1)
        writer.close()

    async with _behind(close, tmp_path) as (_, on_n2):
        await until(lambda: "online" in [m.text for m in on_n2.on(f"{BASE}/status")])
        assert len(accepted) <= 2, len(accepted)  # the probe (and a hedge's, at most)


@pytest.mark.anyio
async def test_a_probe_whose_echo_an_acl_drops_leaves_it_to_the_connect(
        tmp_path: Path) -> None:
    """An ACL lets the probe connect and subscribe but silently drops its echo: the
    probe is answered, then never complete.  That is no reason to stay away: the
    real connect decides (and here succeeds)."""
    acl = tmp_path / "acl"
    # (lines before the first "user" are the anonymous test recorder's)
    acl.write_text(f"topic read #\nuser gateway\ntopic deny {BASE}/status/probe/#\n"
                   f"topic readwrite #\n")
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path, users={"gateway": "s3cret"},
                   settings={"acl_file": str(acl), "allow_anonymous": "true"}) as n1, \
            simulated([ah]) as line, recording(n1, f"{BASE}/status") as rec:
        cfg = _config(line.path, [n1.url])
        cfg["mqtt"] |= {"username": "gateway", "password": "s3cret"}
        async with running(cfg) as gw:
            await until(lambda: "online" in [m.text for m in rec.on(f"{BASE}/status")], 30)
            assert gw.mqtt is not None and gw.mqtt.connected
