"""paho driven from the gateway's event loop (``mqtt_link/driver.py``): no thread of
paho's while the gateway is connected, and a socket whose buffer is full (a broker
that stops reading) loses and reorders nothing; against a real mosquitto."""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import pytest
from support.broker import Mosquitto, recording
from support.harness import running, until

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

    async def before_connect(self, brokers: tuple[Broker, ...]) -> Ready:
        return Ready(brokers[0], None)

    def will(self) -> Message:
        return Message("drv/status", b"offline", 1, True)

    def on_connected(self) -> None:
        pass

    def on_message(self, message: paho.MQTTMessage) -> None:
        pass

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
