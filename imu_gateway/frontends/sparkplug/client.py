"""The Sparkplug B front end: an MQTT session of its own (its own client id, and the
NDEATH as its will) on the brokers of ``mqtt.url``, carrying the ``EdgeNode``'s
messages.  It reads the cache like every front end and adds no bus traffic; commands
go through the gateway's command path (``Gateway.command``), so through the bus
master's queue.  The buses' counters (``Gateway.stats()``) go out as node metrics, in
an NDATA every ``NODE_DATA_EVERY_S`` when they changed.  Each alarm transition (the
cache's ``ALARM`` event) goes out as a DDATA of its own; a DCMD acknowledges an alarm
through the gateway (``Gateway.acknowledge``), when commands are allowed."""

from __future__ import annotations

import asyncio
import json
import logging
import time
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho

from ...cache import ALL_EVENTS, EventKind, Snapshot
from ...commands import CATALOGUE, CommandResult
from ...config import Broker, MqttConfig, SparkplugConfig
from ...errors import RequestFailed
from ...mqtt_link.message import Message
from ...mqtt_link.session import Ready, Session
from ...stats import FrontendCounts
from ...supervise import Frontend
from ..common import GatewayLike
from .host import PrimaryHost
from .metrics import device_rows
from .node import Acknowledge, BdSeq, Device, EdgeNode, Ignored, Refused, Write

log = logging.getLogger("imu_gateway.sparkplug")

#: a birth a primary host's STATE asks for this soon after the last birth waits until
#: then (and is made if the host still says online): a host whose STATE changes
#: back and forth makes at most one birth per this many seconds, never a loop
REBIRTH_HOLD_S = 3.0
#: the buses' counters go out as an NDATA at most this often (and only what changed)
NODE_DATA_EVERY_S = 3.0
#: who acknowledged, in the alarm journal, for an acknowledgement by DCMD (the MQTT
#: broker does not say who published it)
ACK_BY = "sparkplug DCMD"


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
        gid = gateway.config.gateway_id
        kept = Path(sp.bdseq_file) if sp.bdseq_file else None
        self.node = EdgeNode(sp.group_id, gid, devices_of(gateway, sp), BdSeq(kept),
                             [b.name for b in gateway.config.buses])
        self.session = Session(mqtt, sp.client_id or f"imu-gateway-{gid}-sparkplug", self,
                               log, mqtt.queue_size, connect_sent=self.node.connect_sent)
        self.counters, self.pipe = self.session.counters, self.session.pipe
        self.host = PrimaryHost(sp.primary_host_id) if sp.primary_host_id else None
        self.ignored = 0
        self._last_birth = -REBIRTH_HOLD_S  # time.monotonic() of the last birth
        self._held: asyncio.TimerHandle | None = None  # a birth waiting (REBIRTH_HOLD_S)
        self._runner: asyncio.Task[None] | None = None
        self._node_data: asyncio.Task[None] | None = None
        self._unsubscribe: Any = None
        self._commands: set[asyncio.Task[None]] = set()

    @property
    def connected(self) -> bool:
        return self.session.connected

    @property
    def host_online(self) -> bool:
        """No primary host to wait for, or its last STATE on this connection says online."""
        return self.host is None or self.host.online

    async def start(self) -> None:
        self._unsubscribe = self.gateway.cache.subscribe(self._on_cache_event, self.fail,
                                                         kinds=ALL_EVENTS)
        self._runner = self.session.run()
        self.guarded(self._runner)
        self._node_data = asyncio.create_task(self._send_node_data(), name="sparkplug ndata")
        self.guarded(self._node_data)

    async def stop(self) -> None:
        """The NDEATH as the last word, then a clean disconnect (or the will, when it
        is not acknowledged in time)."""
        if self._unsubscribe is not None:
            self._unsubscribe()
        for task in [*self._commands, *([self._node_data] if self._node_data else [])]:
            task.cancel()
        if self._held is not None:
            self._held.cancel()
        last = [self.node.death(_now_ms())] if self.node.born else []
        await self.session.stop(self._runner, last)

    def sensors_changed(self) -> None:
        """A reload changed the sensors: a rebirth on the same MQTT session (same
        bdSeq), as for a Rebirth NCMD: a DDEATH for each device gone, then the NBIRTH
        (seq 0) and a DBIRTH for each device online.  Not born now (not connected, or
        the primary host away): the next births have the new set."""
        gateway = self.gateway
        deaths = self.node.set_devices(devices_of(gateway, self.config),
                                       [b.name for b in gateway.config.buses], _now_ms())
        if not (self.node.born and self.connected and self.host_online):
            return
        for message in deaths:
            self.pipe.send(message)
        log.info("sparkplug: the sensors changed; rebirth with %d devices (bdSeq %d)",
                 len(self.node.devices), self.node.session)
        self._birth()

    # ------------------------------------------------------------ the session's owner

    async def before_connect(self, brokers: tuple[Broker, ...]) -> Ready:
        return Ready(brokers[0], None)

    def will(self) -> Message:
        return self.node.will(_now_ms())

    def on_connected(self) -> None:
        self.pipe.waiting()  # the last connection's messages: their seq is gone with it
        client = self.session.client
        assert client is not None
        for topic in self.node.command_topics:
            client.subscribe(topic, qos=1)
        if self.host is not None:
            self.host.connected()  # offline until its STATE says so (retained: at once)
            for topic in self.host.topics:
                client.subscribe(topic, qos=1)
        else:
            self._birth()

    def _birth(self) -> None:
        self._last_birth = time.monotonic()
        with self.gateway.cache.heard():  # (what waits comes as DDATA after the births)
            births = self.node.birth(self.gateway.cache.snapshots(), self.gateway.stats(),
                                     _now_ms(), self.gateway.alarm_states())
        for message in births:
            self.pipe.send(message)

    def on_message(self, message: paho.MQTTMessage) -> None:
        if self.host is not None and message.topic in self.host.topics:
            self._host_state(message.topic, bytes(message.payload))
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
                if isinstance(write, Acknowledge):
                    self._acknowledge(write)
                    continue
                if isinstance(write, Refused):
                    self.counters.commands += 1
                    self.counters.command_errors += 1
                    self._ignore(f"a DCMD for {write.device}: {write.text}")
                    self._answer(write.device, write.text)
                    continue
                task = asyncio.create_task(self._run(write), name=f"sparkplug {write.command}")
                self._commands.add(task)
                task.add_done_callback(self._commands.discard)

    def _host_state(self, topic: str, data: bytes) -> None:
        assert self.host is not None
        why = self.host.heard(topic, data)
        if why is not None:
            self._ignore(why)
        elif self.host.online:
            self._birth_when_due()
        elif self.node.born:
            # Sparkplug: the node ends its session when its primary host goes; the
            # session reconnects (a new bdSeq) and waits for the host again.
            log.warning("sparkplug: primary host %s is offline; ending this session",
                        self.host.host_id)
            client = self.session.client
            if client is not None:
                death = self.node.death(_now_ms())
                client.publish(death.topic, death.payload, death.qos, death.retain)
                client.disconnect()
            self.node.born = False

    def _birth_when_due(self) -> None:
        """The births the host's online STATE asks for: now, or, within
        ``REBIRTH_HOLD_S`` of the last birth, once that time is up."""
        if self.node.born or self._held is not None:
            return
        wait = self._last_birth + REBIRTH_HOLD_S - time.monotonic()
        if wait <= 0:
            self._birth()
            return
        log.info("sparkplug: primary host %s online again %.1f s after the last birth; "
                 "births in %.1f s", self.host.host_id if self.host else "",
                 REBIRTH_HOLD_S - wait, wait)
        self._held = asyncio.get_running_loop().call_later(wait, self._held_birth)

    def _held_birth(self) -> None:
        """A held birth's time is up: made if the host still says online (this
        connection's latest STATE)."""
        self._held = None
        try:
            if self.connected and self.host_online and not self.node.born:
                self._birth()
        except Exception as exc:  # a bug: the supervisor logs and restarts
            self.fail(exc)

    def _ignore(self, reason: str) -> None:
        self.ignored += 1
        self.session.peers.warning("ignored", "sparkplug: ignored %s", reason)

    async def _run(self, write: Write) -> None:
        spec = CATALOGUE[write.command]
        args = {} if spec.argument is None else {spec.argument: write.value}
        self.counters.commands += 1
        result = await self.gateway.command(write.device, write.command, args)
        if not result.ok:
            self.counters.command_errors += 1
        self._answer(write.device, result_text(result))

    def _acknowledge(self, ack: Acknowledge) -> None:
        """Acknowledge an alarm; its transition goes out (the ``ALARM`` event) before
        the answer in ``Commands/Result``: ``Alarms/{alarm}/Acked: ok``, or
        ``…: nothing_to_acknowledge: …``."""
        self.counters.commands += 1
        try:
            self.gateway.acknowledge(ack.device, ack.alarm, ACK_BY)
        except RequestFailed as exc:
            self.counters.command_errors += 1
            self._answer(ack.device, f"{ack.metric}: {exc.kind.value}: {exc}")
        else:
            self._answer(ack.device, f"{ack.metric}: ok")

    def _answer(self, device: str, text: str) -> None:
        for message in self.node.result(device, text, _now_ms()):
            self.pipe.send(message)

    async def _send_node_data(self) -> None:
        """The buses' counters that changed, every ``NODE_DATA_EVERY_S``."""
        while True:
            await asyncio.sleep(NODE_DATA_EVERY_S)
            if self.connected and self.host_online:
                for message in self.node.node_data(self.gateway.stats(), _now_ms()):
                    self.pipe.send(message)

    # ------------------------------------------------------------ the cache

    def _on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.SETTINGS or not self.connected or not self.host_online:
            return  # (the next births carry what is missed meanwhile, alarms too)
        if kind is EventKind.ALARM:
            assert snap.alarm is not None
            messages = self.node.alarm(snap.alarm, _now_ms())
        else:
            messages = self.node.update(snap, _now_ms())
        for message in messages:
            self.pipe.send(message)

    def stats(self) -> FrontendCounts:
        return {"connected": self.pipe.publishing(), "published": self.counters.published,
                "queued": self.pipe.queued(),
                "dropped": self.pipe.outbox.dropped + self.counters.lost_in_flight,
                "connects": self.counters.connects, "bdseq": self.node.session,
                "commands": self.counters.commands,
                "command_errors": self.counters.command_errors, "ignored": self.ignored}


def devices_of(gateway: GatewayLike, sp: SparkplugConfig) -> list[Device]:
    """The gateway's sensors as Sparkplug devices (at start, and after a reload)."""
    protocols = {s.name: b.protocol for b, s in gateway.config.iter_sensors()}
    alarms: dict[str, list[str]] = {name: [] for name in gateway.sensors}
    for state in gateway.alarm_states():  # (in the gateway's order)
        alarms[state.sensor].append(state.name)
    return [Device(s.name, tuple(device_rows(s, protocols[s.name], sp.allow_commands)),
                   tuple(alarms[s.name]))
            for s in gateway.sensors.values()]


def result_text(result: CommandResult) -> str:
    """A command's ``Commands/Result``: ``{command}: ok``, then the sensor's answer as
    JSON when it has one (``read_settings``: the settings); or
    ``{command}: {kind}: {message}``."""
    if result.ok:
        answer = f" {json.dumps(dict(result.answer), default=str)}" if result.answer else ""
        return f"{result.command}: ok{answer}"
    kind = result.kind.value if result.kind is not None else "error"
    return f"{result.command}: {kind}: {result.error}"
