"""The MQTT client: state, availability, alarms, commands and Home Assistant discovery
(docs/mqtt.md).

The connection (threads, connecting, failover) is a ``mqtt_link.session.Session``; the
way to paho (outbox, control messages, window) its ``mqtt_link.pipe.Pipe``.  Before
each connect, an identity probe makes sure no other gateway holds this id
(``identity``).

Nothing grows while the broker is away.  States wait in ``Outbox``, a bounded queue
that drops its oldest message (and counts it) when full.  The retained control messages
(status, availability, discovery) and command results wait in a queue of their own,
one entry per topic, which goes first and drops nothing.  Only ``WINDOW`` messages are
handed to paho and not yet written (QoS 0) or acknowledged (QoS 1, 2), so paho's own
queues stay small even when a broker stops reading.  After each (re)connect the gateway
status, every sensor's availability and discovery are published anew, then what waited,
then every sensor's latest state: the retained messages are right again whatever was
lost in between.

State messages.  Every new reading, unless ``min_interval_ms`` (at most one message per
interval; the latest reading is sent when the interval ends, so a sensor that goes quiet
is not left showing an older one) or ``deadband`` (only when a listed field moved more
than its band since the last message sent) hold it back.  A status change is always
sent.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any

import paho.mqtt.client as paho
from paho.mqtt.subscribeoptions import SubscribeOptions

from ...cache import EventKind
from ...config import Broker, MqttConfig
from ...mqtt_link import probe
from ...mqtt_link.errors import BrokerUnreached
from ...mqtt_link.message import Message, json_properties
from ...mqtt_link.session import Ready, Session
from ...stats import FrontendCounts
from ...supervise import Frontend
from ..common import GatewayLike, json_bytes
from . import identity
from .alarm_desk import AlarmDesk
from .commands import CommandDesk, ResponseTopics
from .discovery import discovery_configs, setup_of
from .identity import Identity
from .live import sensor_set_change, through_outbox
from .states import StateDesk
from .sweep import SWEEP_S, RetainedSweep
from .topics import (
    ACK_LEAF,
    ALARM_LEAF,
    CONTROL_QOS,
    OFFLINE,
    ONLINE,
    Topics,
    retained_leaves,
)

if TYPE_CHECKING:
    from ...capture import CaptureInfo

log = logging.getLogger("imu_gateway.mqtt")

#: After each connect the retained status is read back this long after, then after
#: twice as long, ``STATUS_CHECKS`` times in all (``_keep_status_right``).
STATUS_CHECK_S, STATUS_CHECKS = 2.0, 4


class MqttClient(Frontend):
    """The gateway's plain MQTT topics; ``start()`` and ``stop()`` on the gateway's loop."""

    name = "mqtt"

    def __init__(self, gateway: GatewayLike, config: MqttConfig) -> None:
        super().__init__()
        self.gateway = gateway
        self.config = config
        self.topics = Topics.of(config, gateway.config.gateway_id)
        self.prefix = self.topics.prefix
        self.status_topic = self.topics.status
        self.session = Session(config, self.client_id, self, log, config.queue_size)
        self.counters, self.pipe = self.session.counters, self.session.pipe
        self.failover, self.outbox = self.session.failover, self.pipe.outbox
        # Made anew when a reload changes the sensors (``sensors_changed``).
        self.discovery = self._discovery()
        self._sensors = dict(gateway.sensors)  # as the retained messages show them
        self.states = StateDesk(gateway, config, self.topics, self.pipe.send,
                                self._send_control, lambda: self.connected, self.pipe.waiting)
        self.alarms = AlarmDesk(gateway, config, self.topics, self._send_control,
                                lambda: self.connected)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: asyncio.Task[None] | None = None
        self._unsubscribe: Any = None
        self._unannounce: Any = None
        self._unsubscribe_alarms: Any = None
        self.sweep = RetainedSweep(
            self.topics, config.discovery_prefix if config.homeassistant_discovery else None,
            self.discovery, retained_leaves(config, gateway.sensors), self._send_control)
        self._sweep_timer: asyncio.TimerHandle | None = None
        self._command_mid: int | None = None  # the command subscription's message id
        self._checker: asyncio.Task[None] | None = None
        self._served: dict[str, bytes] = {}  # the retained messages the probe found
        self._last_broker: Broker | None = None  # the broker of the last connection
        self.identity = Identity(self.topics, self.client_id, self._send_control)
        self.desk = CommandDesk(gateway, config, self._send_control, self.counters,
                                self.session.peers)

    @property
    def connected(self) -> bool:
        return self.session.connected

    def _discovery(self) -> dict[str, Any]:
        return discovery_configs(setup_of(self.gateway.config, self.topics)) \
            if self.config.homeassistant_discovery else {}

    @property
    def taking_commands(self) -> bool:
        """Connected, and the broker has granted the command subscription: a command
        published from now on reaches the gateway.  (Between CONNACK and SUBACK one
        would be dropped by the broker, having no subscriber yet.)"""
        return self.connected and self._command_mid in self.session.granted

    @property
    def _client(self) -> paho.Client | None:
        return self.session.client

    # ------------------------------------------------------------ topics

    def sensor_topic(self, sensor: str, leaf: str) -> str:
        return self.topics.sensor(sensor, leaf)

    # ------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Connect in the background (again, after ``stop``: the supervisor restarts
        a failed client this way)."""
        self._loop = asyncio.get_running_loop()
        self.desk.cancel()
        self._unsubscribe = self.gateway.cache.subscribe(self.states.on_cache_event, self.fail)
        captures = self.gateway.captures
        self._unannounce = captures.subscribe(self._announce_capture) if captures else None
        self._unsubscribe_alarms = self.gateway.cache.subscribe(
            self.alarms.on_cache_event, self.fail, kinds={EventKind.ALARM})
        self._runner = self.session.run()
        self.guarded(self._runner)

    def _announce_capture(self, info: CaptureInfo) -> None:
        """A new capture (docs/mqtt.md): queued like a result, each one its own."""
        self.pipe.send_control(Message(self.topics.captures, json_bytes(info.to_json()),
                                       CONTROL_QOS, False), f"capture {info.id}")

    @property
    def client_id(self) -> str:
        return self.config.client_id or f"imu-gateway-{self.gateway.config.gateway_id}"

    async def stop(self) -> None:
        """Say ``offline`` (every sensor's availability, then the status), then
        disconnect; or, when that is not acknowledged in time, leave it to the will."""
        for unsubscribe in (self._unsubscribe, self._unsubscribe_alarms, self._unannounce):
            if unsubscribe is not None:
                unsubscribe()
        if self._checker is not None:
            self._checker.cancel()
        self.states.cancel()
        self.desk.cancel()
        offline = [Message(self.sensor_topic(name, "availability"), OFFLINE, CONTROL_QOS, True)
                   for name in self.gateway.sensors]
        await self.session.stop(self._runner, [
            *offline, Message(self.status_topic, OFFLINE, CONTROL_QOS, True)])

    def sensors_changed(self) -> None:
        """A reload changed the sensors (``live.py``): on the same connection, the
        discovery configs and retained topics that changed are said.  While the broker
        is away, nothing is queued: the next connect's announcement and sweep, made
        from the new sets, do it."""
        gateway, leaves = self.gateway, retained_leaves(self.config, self.gateway.sensors)
        discovery, sensors = self._discovery(), dict(gateway.sensors)
        change = sensor_set_change(self.topics, (self.discovery, discovery),
                                   (self.sweep.leaves, leaves), (self._sensors, sensors))
        self.discovery = self.sweep.discovery = discovery
        self.sweep.leaves, self._sensors = leaves, sensors
        self.desk.response_topics = ResponseTopics.of(self.config, gateway.config.gateway_id,
                                                      sensors)
        if self.connected:
            described = json_properties(self.config)
            for topic in change.swept:
                self._send_control(Message(topic, b"", CONTROL_QOS, True))
            for topic in change.configs:
                self._send_control(Message(topic, json_bytes(discovery[topic]), CONTROL_QOS,
                                           True, described))
            for topic in change.cleared:
                clear = Message(topic, b"", CONTROL_QOS, True)
                (self.pipe.send if through_outbox(self.topics, topic) else self._send_control)(
                    clear)
        self.states.sensors_changed(change.announced)
        self.alarms.announce(change.announced)
        log.info("mqtt: the sensors changed, the connection stays: %s", change.summary())

    # ------------------------------------------------------------ the session's owner

    async def before_connect(self, brokers: tuple[Broker, ...]) -> Ready:
        """The first of ``brokers`` to answer the probe.  Another gateway holding this
        id (found now, or while connected): stay away and look again later."""
        if self.identity.held_off:
            self.identity.held_off = False
            return Ready(brokers[0], identity.RIVAL_WAIT)
        probed = await self.identity.rival(brokers, self.session.make_client,
                                           [f"{self.prefix}/#", *self.discovery])
        # what that broker serves already need not be said again: the nodes of a
        # cluster share their retained messages, and NATS holds every later packet of
        # a connection while it stores one (up to 4 s each while it recovers a node).
        # But the status, at this process's first connect and back on the broker of
        # its last: a broker that has not yet seen the last connection (of this
        # process, or of a crashed predecessor) go takes it over as this one connects
        # and publishes its will (offline).  A move to another node keeps the
        # status that node serves (a late will is answered: ``on_message``).
        self._served = dict(probed.served)
        if self._last_broker in (None, probed.broker):
            self._served.pop(self.status_topic, None)
        if probed.rival is None:
            return Ready(probed.broker, None)
        self.identity.held_off = False
        return Ready(probed.broker, identity.RIVAL_WAIT)

    def will(self) -> Message:
        return Message(self.status_topic, OFFLINE, CONTROL_QOS, True)

    def on_connected(self) -> None:
        self._last_broker = self.failover.current
        self._subscribe()
        self._announce()
        if self._checker is not None:
            self._checker.cancel()
        self._checker = asyncio.create_task(self._keep_status_right(), name="mqtt status")
        self.guarded(self._checker)

    async def _keep_status_right(self) -> None:
        """Read the retained status back a few times after a connect, and say online
        again when it is not.  A broker cluster can store retained messages out of
        order while it recovers from a node's loss (NATS 2.9 did, in the fleet test:
        the will of the connection on the dead node stored after the online of the
        new one), and then serves the wrong status to every new subscriber."""
        wait, status = STATUS_CHECK_S, self.status_topic
        for _ in range(STATUS_CHECKS):
            await asyncio.sleep(wait)
            wait *= 2
            # every node of the list: a cluster's nodes can disagree, and a subscriber
            # may be on any of them
            for broker in self.config.brokers:
                if not self.connected or self.session.stopping:
                    return
                try:
                    # (a client id of its own: a probe of the connect's may still be
                    # connecting, and a second connection with its id would take over)
                    found = await probe.read_retained(
                        self.session.make_client, broker, f"{self.identity.probe_id}-g",
                        [status])
                except BrokerUnreached as failed:
                    if failed.kind == "unreachable":
                        continue  # a node that is down: it has nothing to serve
                    found = {}  # up but not answering (recovering): say it again anyway
                except (OSError, TimeoutError, ValueError):
                    continue  # asked again at the next check
                log.debug("mqtt: %s serves this gateway's retained status as %r", broker,
                          found.get(status))
                if found.get(status) != ONLINE and self.connected:
                    log.warning("mqtt: %s serves this gateway's retained status as %r, not "
                                "online (a broker cluster that stored messages out of "
                                "order?); saying online again", broker,
                                found.get(status, b"").decode(errors="replace"))
                    self._send_control(Message(status, ONLINE, CONTROL_QOS, True))
                    break

    def _subscribe(self) -> None:
        assert self._client is not None
        for topic in self.identity.claim_topics:  # a rival's claim, live (QoS 0: as probe)
            self._client.subscribe(topic, qos=0)
        # A cluster may publish the will of the connection it lost after this one has
        # said online on another node: heard live, it is answered (``on_message``).
        self._client.subscribe(self.status_topic, qos=0)
        if self.config.allow_commands:
            # QoS 0: the session is clean, so a QoS 1 subscription would bring no
            # redelivery (that needs a session that outlives the connection), and NATS
            # makes a JetStream consumer for each one, holding every later packet of
            # the connection meanwhile: 0.4-0.8 s at each connect, 4 s while a lost
            # node's groups elect new leaders (docs/mqtt.md).
            # MQTT 5: the retain flag as published, so that a retained command is
            # known as one even when it arrives live (3.1.1 brokers clear the flag).
            # The commands and the alarms' acknowledgements, in one SUBSCRIBE.
            topics = (f"{self.prefix}/+/cmd/+", f"{self.prefix}/+/{ALARM_LEAF}/+/{ACK_LEAF}")
            if self.config.protocol == "5":
                _, self._command_mid = self._client.subscribe(
                    [(t, SubscribeOptions(qos=0, retainAsPublished=True)) for t in topics])
            else:
                _, self._command_mid = self._client.subscribe([(t, 0) for t in topics])
        assert self._loop is not None
        self.sweep.start(self._client, self._loop.time())
        if self._sweep_timer is not None:  # an earlier connection's
            self._sweep_timer.cancel()
        self._sweep_timer = self._loop.call_later(SWEEP_S, self._end_sweep)

    def _end_sweep(self) -> None:
        if self._client is not None and self.connected:
            self.sweep.end(self._client)

    def _announce(self) -> None:
        """Everything retained, anew: after every connect, but what the broker
        already served as it is when the probe asked (a node of the same cluster:
        ``_send_control``).  The control messages go first; then each sensor's latest
        state (the states that waited are old news by now: ``Pipe.connected_anew``)."""
        try:
            self.identity.claim_it()
            self._send_control(Message(self.status_topic, ONLINE, CONTROL_QOS, True))
            described = json_properties(self.config)  # one for all (paho packs it per send)
            for topic, payload in self.discovery.items():
                self._send_control(Message(topic, json_bytes(payload), CONTROL_QOS, True,
                                           described))
            self.states.announce()
            self.alarms.announce()
        finally:
            self._served = {}  # the probe's: for this announcement only

    def on_message(self, message: paho.MQTTMessage) -> None:
        topic = message.topic
        parts = topic.removeprefix(f"{self.prefix}/").split("/")
        ours = topic.startswith(self.prefix + "/")
        if ours and len(parts) == 3 and parts[1] == "cmd":
            self.desk.take(message, parts[0], parts[2])
        elif ours and len(parts) == 4 and parts[1] == ALARM_LEAF and parts[3] == ACK_LEAF:
            self.desk.take_ack(message, parts[0], parts[2])
        elif topic in self.identity.claim_topics:
            if self.identity.seen(message) and self._client is not None:
                self._client.disconnect()  # cleanly: no will, the status stays theirs
        elif topic == self.status_topic:
            if message.payload == OFFLINE and not message.retain and self.connected \
                    and not self.session.stopping:
                log.warning("mqtt: the broker published this gateway's will (a late one, "
                            "from a connection it lost) while it is connected; its "
                            "status is online again")
                self._send_control(Message(self.status_topic, ONLINE, CONTROL_QOS, True))
        elif self._loop is not None:
            self.sweep.take(message, self._loop.time())

    # ------------------------------------------------------------ stats

    @property
    def publishing(self) -> bool:
        return self.pipe.publishing()

    def _send_control(self, message: Message, key: str | None = None) -> None:
        if message.retain and self._served.get(message.topic) == message.payload:
            # the broker serves it so already (``_served``: from the probe before this
            # connect until the announcement after it); an older one still waiting
            # for that key would undo it
            self.pipe.control.pop(key or message.topic, None)
            return
        self.pipe.send_control(message, key)

    def stats(self) -> FrontendCounts:
        return {"connected": self.publishing, "published": self.counters.published,
                "queued": self.pipe.queued(),
                "dropped": self.outbox.dropped + self.counters.lost_in_flight
                + self.states.missed,
                "in_flight": self.pipe.in_window(), "connects": self.counters.connects,
                "commands": self.counters.commands,
                "command_errors": self.counters.command_errors,
                "undeliverable": self.counters.undeliverable,
                "ignored_commands": self.counters.ignored}
