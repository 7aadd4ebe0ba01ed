"""paho driven from the gateway's event loop (``mqtt_link/driver.py``): no thread of
paho's while the gateway is connected, a socket whose buffer is full (a broker that
stops reading) loses and reorders nothing, and a TLS record holding several MQTT
packets is read whole; against a real mosquitto."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import ssl
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest
from paho.mqtt import publish
from support.broker import Mosquitto, Tls, make_tls, recording
from support.harness import free_port, running, until

from imu_gateway.config import Broker, MqttConfig
from imu_gateway.model import Series, WireProtocol
from imu_gateway.mqtt_link.message import Message
from imu_gateway.mqtt_link.pipe import WINDOW
from imu_gateway.mqtt_link.session import Ready, Session
from imu_gateway.simulator import make_sensor, simulated

#: the name paho gives its network thread (``loop_start``), before the client id
PAHO_THREAD = "paho-mqtt-client-"


class Owner:
    """The least a session asks of its front end: connect to the first broker."""

    def __init__(self) -> None:
        self.failures: list[BaseException] = []
        self.messages: list[tuple[str, bytes]] = []

    async def before_connect(self, brokers: tuple[Broker, ...]) -> Ready:
        return Ready(brokers[0], None)

    def will(self) -> Message:
        return Message("drv/status", b"offline", 1, True)

    def on_connected(self) -> None:
        pass

    def on_message(self, message: paho.MQTTMessage) -> None:
        self.messages.append((message.topic, bytes(message.payload)))

    def fail(self, exc: BaseException) -> None:
        self.failures.append(exc)


@contextmanager
def stopped(broker: Mosquitto) -> Iterator[None]:
    """The broker's process is stopped (SIGSTOP): it reads nothing, its socket
    buffers fill; it goes on when the block ends."""
    assert broker.process is not None
    os.kill(broker.process.pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(broker.process.pid, signal.SIGCONT)


@pytest.mark.anyio
async def test_a_broker_that_stops_reading_loses_and_reorders_nothing(
        tmp_path: Path) -> None:
    # a window of 256 kB messages (25 MB) is more than loopback's socket buffers hold
    count, pad = 2 * WINDOW + 17, bytes(256 * 1024)
    owner = Owner()
    with Mosquitto(tmp_path) as broker, recording(broker, "drv/data", qos=1) as rec:
        session = Session(MqttConfig(url=broker.url), "drv", owner,
                          logging.getLogger("test"), queue_size=count)
        runner = session.run()
        try:
            await until(lambda: session.connected)
            with stopped(broker):
                for n in range(count):
                    session.pipe.send(Message("drv/data", n.to_bytes(4, "big") + pad, 1, False))
                client = session.client
                assert client is not None
                # the socket takes no more: paho holds the rest in its queue, and the
                # pipe the messages past its window
                await until(lambda: client.want_write()
                            and session.pipe.in_window() == WINDOW)
                assert len(session.pipe.outbox) == count - WINDOW
            await until(lambda: len(rec.on("drv/data")) == count, timeout=60)
            got = [int.from_bytes(m.payload[:4], "big") for m in rec.on("drv/data")]
            assert got == list(range(count))
            assert all(len(m.payload) == 4 + len(pad) for m in rec.on("drv/data"))
            await until(lambda: session.counters.written == count)
            assert session.counters.lost_in_flight == session.pipe.outbox.dropped == 0
            assert session.counters.connects == 1 and not owner.failures
        finally:
            await session.stop(runner, [])


@pytest.mark.anyio
async def test_no_thread_of_paho_runs_while_the_gateway_is_connected(
        tmp_path: Path) -> None:
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with Mosquitto(tmp_path) as broker, simulated([ah]) as line:
        # both MQTT front ends: the plain topics (which probe first) and Sparkplug
        config: dict[str, Any] = {
            "gateway_id": "gw",
            "buses": [{"name": "a", "port": line.path, "baudrate": 115200,
                       "protocol": "native",
                       "sensors": [{"name": "ah", "series": "AH", "poll_hz": 20}]}],
            "mqtt": {"url": broker.url, "homeassistant_discovery": True,
                     "sparkplug": {"group_id": "g"}}}
        async with running(config) as gw:
            await until(lambda: gw.mqtt is not None and gw.mqtt.connected
                        and gw.sparkplug is not None and gw.sparkplug.connected
                        and gw.mqtt.counters.written > 0 and gw.sparkplug.counters.written > 0)
            written = gw.mqtt.counters.written  # type: ignore[union-attr]
            await until(lambda: gw.mqtt is not None and gw.mqtt.counters.written > written)
            assert [t.name for t in threading.enumerate()
                    if t.name.startswith(PAHO_THREAD)] == []


class TlsFront:
    """A TLS-terminating relay in front of a plain broker, as stunnel or a load
    balancer would be.  While ``hold`` is set, what the broker sends is kept; at
    ``release`` it goes on in one write: several MQTT packets in one TLS record."""

    def __init__(self, tls: Tls, broker_port: int) -> None:
        self.tls, self.broker_port, self.port = tls, broker_port, free_port()
        self.hold = False
        self.held = bytearray()
        self._to_client: asyncio.StreamWriter | None = None
        self._writers: list[asyncio.StreamWriter] = []
        self._relays: list[asyncio.Task[None]] = []
        self._server: asyncio.Server | None = None

    async def __aenter__(self) -> TlsFront:
        context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
        context.load_cert_chain(self.tls.server_cert, self.tls.server_key)
        self._server = await asyncio.start_server(self._relay, "127.0.0.1", self.port,
                                                  ssl=context)
        return self

    async def __aexit__(self, *_: object) -> None:
        assert self._server is not None
        self._server.close()
        for writer in self._writers:
            writer.close()
        await asyncio.gather(*self._relays, return_exceptions=True)

    def release(self) -> None:
        assert self._to_client is not None
        self.hold = False
        self._to_client.write(bytes(self.held))
        self.held.clear()

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._to_client = writer
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.broker_port)
        self._writers += [writer, up_writer]
        self._relays.append(asyncio.current_task())  # type: ignore[arg-type]

        async def copy(source: asyncio.StreamReader, sink: asyncio.StreamWriter,
                       held: bool) -> None:
            with contextlib.suppress(OSError, asyncio.IncompleteReadError):
                while data := await source.read(65536):
                    if held and self.hold:
                        self.held += data
                    else:
                        sink.write(data)
            sink.close()

        await asyncio.gather(copy(reader, up_writer, False), copy(up_reader, writer, True))


@pytest.mark.anyio
async def test_several_packets_in_one_tls_record_are_all_read(tmp_path: Path) -> None:
    # one TLS record is decrypted whole, and paho reads one packet of it per read:
    # the rest waits in the SSL socket (pending()), with nothing more on the wire
    count = 40
    tls = make_tls(tmp_path / "tls")
    owner = Owner()
    with Mosquitto(tmp_path) as broker:
        await asyncio.to_thread(publish.multiple, [
            {"topic": f"drv/in/{n}", "payload": f"{n}", "qos": 1, "retain": True}
            for n in range(count)], hostname="127.0.0.1", port=broker.port)
        async with TlsFront(tls, broker.port) as front:
            config = MqttConfig(url=f"mqtts://127.0.0.1:{front.port}", ca_file=str(tls.ca),
                                certfile=str(tls.client_cert), keyfile=str(tls.client_key))
            session = Session(config, "drv", owner, logging.getLogger("test"), 10)
            runner = session.run()
            try:
                await until(lambda: session.connected)
                front.hold = True
                assert session.client is not None
                # (QoS 0: mosquitto holds back QoS 1 messages past 20 in flight)
                session.client.subscribe("drv/in/#", 0)
                # the SUBACK (5 bytes) and every retained PUBLISH (QoS 0: 2 bytes of
                # header, the topic with its length, the payload)
                size = 5 + sum(2 + 2 + len(f"drv/in/{n}") + len(f"{n}")
                               for n in range(count))
                await until(lambda: len(front.held) >= size)
                assert len(front.held) == size
                front.release()
                await until(lambda: len(owner.messages) == count)
                assert sorted(owner.messages) == sorted(
                    (f"drv/in/{n}", f"{n}".encode()) for n in range(count))
            finally:
                await session.stop(runner, [])
