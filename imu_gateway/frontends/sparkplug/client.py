"""The Sparkplug B front end: an MQTT session of its own (its own client id, and the
NDEATH as its will) on the brokers of ``mqtt.url``, carrying the ``EdgeNode``'s
messages.  It reads the cache like every front end and adds no bus traffic; commands
go through the gateway's command path (``Gateway.command``), so through the bus
master's queue."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho

from ...cache import EventKind, Snapshot
from ...commands import CATALOGUE
from ...config import Broker, MqttConfig, SparkplugConfig
from ...stats import FrontendCounts
from ...supervise import Frontend
from ..common import GatewayLike
from ..mqtt_session import Ready, Session
from ..mqtt_topics import Message
from .metrics import device_rows
from .node import BdSeq, Device, EdgeNode, Ignored, Write

log = logging.getLogger("imu_gateway.sparkplug")


def _now_ms() -> int:
    return int(time.time() * 1000)


class SparkplugClient(Frontend):
    """The gateway as a Sparkplug B edge node."""

    name = "sparkplug"

    def __init__(self, gateway: GatewayLike, mqtt: MqttConfig) -> None:
        super().__init__()
        assert mqtt.sparkplug is not None
        self.gateway, self.config = gateway, mqtt.sparkplug
        sp: SparkplugConfig = mqtt.sparkplug
        protocols = {s.name: b.protocol for b, s in gateway.config.iter_sensors()}
        devices = [Device(s.name, tuple(device_rows(s, protocols[s.name], sp.allow_commands)))
                   for s in gateway.sensors.values()]
        gid = gateway.config.gateway_id
        kept = Path(sp.bdseq_file) if sp.bdseq_file else None
        self.node = EdgeNode(sp.group_id, gid, devices, BdSeq(kept))
        self.session = Session(mqtt, sp.client_id or f"imu-gateway-{gid}-sparkplug", self,
                               log, mqtt.queue_size)
        self.counters, self.pipe = self.session.counters, self.session.pipe
        self.host_online = sp.primary_host_id is None  # no host to wait for
        self.ignored = 0
        self._runner: asyncio.Task[None] | None = None
        self._unsubscribe: Any = None
        self._commands: set[asyncio.Task[None]] = set()

    @property
    def connected(self) -> bool:
        return self.session.connected

    async def start(self) -> None:
        self._unsubscribe = self.gateway.cache.subscribe(self._on_cache_event, self.fail)
        self._runner = self.session.run()
        self.guarded(self._runner)

    async def stop(self) -> None:
        """The NDEATH as the last word, then a clean disconnect (or the will, when it
        is not acknowledged in time)."""
        if self._unsubscribe is not None:
            self._unsubscribe()
        for task in self._commands:
            task.cancel()
        last = [self.node.death()] if self.node.born else []
        await self.session.stop(self._runner, last)

    # ------------------------------------------------------------ the session's owner

    async def before_connect(self, brokers: tuple[Broker, ...]) -> Ready:
        return Ready(brokers[0], None)

    def will(self) -> Message:
        return self.node.connected()

    def on_connected(self) -> None:
        self.pipe.waiting()  # the last connection's messages: their seq is gone with it
        client = self.session.client
        assert client is not None
        for topic in self.node.command_topics:
            client.subscribe(topic, qos=1)
        if self.config.primary_host_id is not None:
            self.host_online = False  # until its STATE says so (retained: at once)
            for topic in self.node.state_topics(self.config.primary_host_id):
                client.subscribe(topic, qos=1)
        else:
            self._birth()

    def _birth(self) -> None:
        for message in self.node.birth(self.gateway.cache.snapshots(), _now_ms()):
            self.pipe.send(message)

    def on_message(self, message: paho.MQTTMessage) -> None:
        host = self.config.primary_host_id
        if host is not None and message.topic in self.node.state_topics(host):
            self._host_state(EdgeNode.host_online(bytes(message.payload)))
            return
        outcome = self.node.command(message.topic, bytes(message.payload))
        if outcome is True and not self.host_online:
            # (Sparkplug: nothing is published while the primary host is away; its
            # coming back births the node anyway)
            self._ignore("a rebirth (NCMD) while the primary host is offline")
        elif outcome is True:
            log.info("sparkplug: rebirth asked for (NCMD)")
            self._birth()
        elif isinstance(outcome, Ignored):
            self._ignore(outcome.reason)
        elif not self.config.allow_commands:
            self._ignore("a DCMD, and commands are not allowed (mqtt.sparkplug.allow_commands)")
        elif isinstance(outcome, list):
            for write in outcome:
                task = asyncio.create_task(self._run(write), name=f"sparkplug {write.command}")
                self._commands.add(task)
                task.add_done_callback(self._commands.discard)

    def _host_state(self, online: bool | None) -> None:
        if online is None:
            self._ignore("a primary host STATE that is neither online nor offline")
        elif online and not self.host_online:
            self.host_online = True
            self._birth()
        elif not online and self.host_online:
            # Sparkplug: the node ends its session when its primary host goes; the
            # session reconnects (a new bdSeq) and waits for the host again.
            self.host_online = False
            log.warning("sparkplug: primary host %s is offline; ending this session",
                        self.config.primary_host_id)
            client = self.session.client
            if client is not None and self.node.born:
                death = self.node.death()
                client.publish(death.topic, death.payload, death.qos, death.retain)
                client.disconnect()

    def _ignore(self, reason: str) -> None:
        self.ignored += 1
        self.session.peers.warning("ignored", "sparkplug: ignored %s", reason)

    async def _run(self, write: Write) -> None:
        spec = CATALOGUE[write.command]
        args = {} if spec.argument is None else {spec.argument: write.value}
        self.counters.commands += 1
        result = await self.gateway.command(write.device, write.command, args)
        if result.ok:
            text = f"{write.command}: ok"
        else:
            self.counters.command_errors += 1
            kind = result.kind.value if result.kind is not None else "error"
            text = f"{write.command}: {kind}: {result.error}"
        for message in self.node.result(write.device, text, _now_ms()):
            self.pipe.send(message)

    # ------------------------------------------------------------ the cache

    def _on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.SETTINGS or not self.connected or not self.host_online:
            return
        for message in self.node.update(snap, _now_ms()):
            self.pipe.send(message)

    def stats(self) -> FrontendCounts:
        return {"connected": self.pipe.publishing(), "published": self.counters.published,
                "queued": self.pipe.queued(),
                "dropped": self.pipe.outbox.dropped + self.counters.lost_in_flight,
                "connects": self.counters.connects, "bdseq": self.node.session,
                "commands": self.counters.commands,
                "command_errors": self.counters.command_errors, "ignored": self.ignored}
