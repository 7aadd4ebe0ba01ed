"""Sparkplug B with a primary host (docs/sparkplug.md, "Primary host"): the test is
the host, on a real mosquitto, and plays what made real nodes flap: STATE messages
delivered late (older timestamps), a 2.2 ``STATE/{host}`` left ``OFFLINE`` beside a
3.0 host's online, and a broker that goes away for a few seconds.  The gateway talks
to the broker through a relay (``ConnectTap``) that keeps the will of every CONNECT
packet it sent, so bdSeq can be checked against the CONNECTs themselves.  Payloads are
read with Eclipse Tahu's decoder."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from support.broker import Mosquitto, Recorder, recording
from support.harness import free_port, running, until
from support.tahu import Tahu
from test_sparkplug import READING, SP, _config, kind, metric, node_messages

from imu_gateway.frontends.sparkplug.host import PrimaryHost
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated

T = 1_700_000_000_000  # the host's session timestamps: T, then later ones
STATE_3, STATE_2 = f"{SP}/STATE/scada", "STATE/scada"


@pytest.fixture(scope="module")
def tahu() -> Iterator[Tahu]:
    codec = Tahu()
    yield codec
    codec.close()


def _varint(data: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, i


def will_payload(body: bytes) -> bytes | None:
    """The will payload of a CONNECT packet (its body, after the fixed header):
    MQTT 3.1.1 or 5."""
    i = 2 + int.from_bytes(body[0:2])  # the protocol name
    level, flags = body[i], body[i + 1]
    i += 4  # level, flags, keep alive
    if level == 5:  # the connect properties
        n, i = _varint(body, i)
        i += n
    i += 2 + int.from_bytes(body[i:i + 2])  # the client id
    if not flags & 0x04:
        return None
    if level == 5:  # the will properties
        n, i = _varint(body, i)
        i += n
    i += 2 + int.from_bytes(body[i:i + 2])  # the will topic
    n = int.from_bytes(body[i:i + 2])
    return body[i + 2:i + 2 + n]


class ConnectTap:
    """A TCP relay to the broker that keeps the will of every CONNECT sent through it.
    ``shut()`` stops listening (a connect is refused, as by a broker that is down) and
    drops what it relays; ``open()`` listens again on the same port."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = free_port()
        self.wills: list[bytes | None] = []  # one per CONNECT packet received
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    async def open(self) -> None:
        self._server = await asyncio.start_server(self._relay, "127.0.0.1", self.port)

    def shut(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        for writer in list(self._writers):
            writer.close()

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        try:
            head = await reader.readexactly(1)
            raw, length = b"", 0
            for shift in range(0, 28, 7):  # the remaining length
                byte = await reader.readexactly(1)
                raw += byte
                length |= (byte[0] & 0x7F) << shift
                if not byte[0] & 0x80:
                    break
            body = await reader.readexactly(length)
            if head[0] >> 4 == 1:  # CONNECT
                self.wills.append(will_payload(body))
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        except (OSError, asyncio.IncompleteReadError):
            writer.close()
            self._writers.discard(writer)
            return
        self._writers.add(up_writer)
        up_writer.write(head + raw + body)
        await asyncio.gather(_copy(reader, up_writer), _copy(up_reader, writer))
        self._writers -= {writer, up_writer}


async def _copy(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    with contextlib.suppress(OSError, asyncio.IncompleteReadError):
        while data := await source.read(65536):
            sink.write(data)
            await sink.drain()
    sink.close()


def _say(host: Recorder, online: bool, timestamp: int) -> None:
    """The host's 3.0 STATE, retained, as a host publishes it."""
    host.client.publish(STATE_3, json.dumps({"online": online, "timestamp": timestamp}),
                        1, True)


@pytest.mark.anyio
async def test_late_states_a_2_2_topic_and_a_broker_outage_make_no_flapping(
        tmp_path: Path, tahu: Tahu) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200, source=hold(READING))
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line, \
            recording(broker, f"{SP}/#") as host:

        def count(what: str) -> int:
            return [kind(m) for m in node_messages(host)].count(what)

        tap = ConnectTap(broker.port)
        await tap.open()
        config = _config(line.path, broker, primary_host_id="scada")
        config["mqtt"]["url"] = f"mqtt://127.0.0.1:{tap.port}"
        # a host that speaks 3.0, and the OFFLINE its 2.2 days left retained
        host.client.publish(STATE_2, b"OFFLINE", 1, True)
        _say(host, True, T)
        try:
            async with running(config) as gw:
                sp = gw.sparkplug
                assert sp is not None
                # 2.2 OFFLINE beside 3.0 online: born once, and it stays (20 Hz: 2 s)
                await until(lambda: count("NBIRTH") == 1)
                await until(lambda: sp.ignored == 1)  # the 2.2 OFFLINE
                await until(lambda: count("DDATA") >= 40, 30)
                assert (count("NBIRTH"), count("NDEATH")) == (1, 0)
                # an offline older than the online taken: a late will, ignored
                _say(host, False, T - 1000)
                await until(lambda: sp.ignored == 2)
                mark = count("DDATA")
                await until(lambda: count("DDATA") >= mark + 20, 30)
                assert (count("NBIRTH"), count("NDEATH")) == (1, 0)
                # the host goes: NDEATH, and a new connection that waits
                _say(host, False, T + 1000)
                await until(lambda: count("NDEATH") == 1)
                await until(lambda: sp.counters.connects == 2 and sp.ignored == 3)  # 2.2's
                # an online older than that offline, and 2.2's ONLINE: neither births
                _say(host, True, T + 500)
                await until(lambda: sp.ignored == 4)
                host.client.publish(STATE_2, b"ONLINE", 1, True)
                await until(lambda: sp.ignored == 5)
                assert count("NBIRTH") == 1
                # the host is back
                _say(host, True, T + 2000)
                await until(lambda: count("NBIRTH") == 2)
                # the connection is cut: the broker publishes the will; then the broker
                # goes for a few failed tries (no CONNECT sent), and comes back
                tap.shut()
                await until(lambda: count("NDEATH") == 2)
                broker.stop()
                await until(lambda: sp.session.failover.failures >= 3, 30)
                broker.start()
                await tap.open()
                # the host too (the broker kept nothing), beside its old 2.2 OFFLINE
                await until(lambda: host.client.is_connected(), 30)
                host.client.publish(STATE_2, b"OFFLINE", 1, True)
                _say(host, True, T + 3000)
                await until(lambda: count("NBIRTH") == 3, 30)
                mark = count("DDATA")
                await until(lambda: count("DDATA") >= mark + 40, 30)
                assert (count("NBIRTH"), count("NDEATH")) == (3, 2)
        finally:
            tap.shut()
        got = [(kind(m), tahu.decode(m.payload)) for m in node_messages(host)]
    wills = [metric(tahu.decode(w), "bdSeq")["value"] for w in tap.wills if w is not None]
    assert len(wills) == len(tap.wills) == 3, wills  # three connections, three CONNECTs
    assert wills == [0, 1, 2]  # one more per CONNECT sent: none for the refused tries
    births = [metric(p, "bdSeq")["value"] for k, p in got if k == "NBIRTH"]
    deaths = [metric(p, "bdSeq")["value"] for k, p in got if k == "NDEATH"]
    # the host's going, the will of the cut connection, the clean stop
    assert births == [0, 1, 2] and deaths == [0, 1, 2]


def test_which_state_counts() -> None:
    """The rules of docs/sparkplug.md, message by message."""
    host = PrimaryHost("scada")
    v3, v2 = host.topics

    def state(online: bool, timestamp: int) -> bytes:
        return json.dumps({"online": online, "timestamp": timestamp}).encode()

    assert host.heard(v2, b"ONLINE") is None and host.online  # 2.2 only, so far: heard
    assert host.heard(v3, state(True, T)) is None and host.online
    assert "speaks 3.0" in str(host.heard(v2, b"OFFLINE")) and host.online
    assert "older" in str(host.heard(v3, state(False, T - 1))) and host.online
    assert host.heard(v3, state(False, T)) is None and not host.online  # its will: same time
    assert "older" in str(host.heard(v3, state(True, T - 5))) and not host.online
    host.connected()
    assert host.heard(v3, state(True, T + 1)) is None and host.online
    host.connected()  # a new connection waits for a STATE of its own
    assert not host.online
    assert host.heard(v3, b'{"online": true}') is None and host.online  # no time: taken
    assert "boolean" in str(host.heard(v3, b'{"online": 1, "timestamp": 9}'))
