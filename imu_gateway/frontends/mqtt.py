"""The MQTT client: state, availability, commands and Home Assistant discovery
(docs/mqtt.md).

Threads.  paho-mqtt's network loop runs on its own thread (``loop_start``); everything
else here runs on the gateway's event loop, where the cache calls its listeners.  paho's
callbacks only hand their event over (``call_soon_threadsafe``), so no state of this
module is written from two threads: paho's thread increments one counter (``written``)
and reads one flag (``Pipe.waiting_for_window``).

Connecting.  The connect itself (TCP, TLS, CONNECT) is ours, in an executor, to the
brokers of ``mqtt.url`` in turn with a back-off (``mqtt_failover``): paho's own
automatic reconnect swallows the reason a connection failed, and a user looking at a
TLS or password problem needs that reason.  Each distinct failure is logged once; the retries
after it are quiet, and "connected" is logged on the way back.

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
import contextlib
import logging
from collections import deque
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode
from paho.mqtt.subscribeoptions import SubscribeOptions

from ..config import Broker, MqttConfig
from ..errors import BrokerUnreached
from ..stats import FrontendCounts
from ..supervise import Frontend, PeerLog
from . import mqtt_identity
from .common import GatewayLike, json_bytes
from .mqtt_commands import CommandDesk
from .mqtt_discovery import discovery_configs, setup_of
from .mqtt_failover import Failover
from .mqtt_identity import Identity, reason_of
from .mqtt_states import StateDesk
from .mqtt_sweep import SWEEP_S, RetainedSweep
from .mqtt_topics import (
    CONTROL_QOS,
    OFFLINE,
    ONLINE,
    Counters,
    Message,
    Topics,
    json_properties,
    retained_leaves,
)

log = logging.getLogger("imu_gateway.mqtt")

KEEPALIVE_S = 30
#: a broker that says nothing after CONNECT (a TLS port, say); the probe's wait too
CONNACK_TIMEOUT = mqtt_identity.PROBE_TIMEOUT
WINDOW = 100  # messages handed to paho and not yet written or acknowledged
#: messages handed to paho and none written for this long: publishing does not work
STALLED_S = 2 * KEEPALIVE_S


class Outbox:
    """A bounded FIFO: when full, the oldest message goes and is counted."""

    def __init__(self, size: int) -> None:
        self._messages: deque[Message] = deque()
        self.size = size
        self.dropped = 0

    def put(self, message: Message) -> None:
        self._messages.append(message)
        if len(self._messages) > self.size:
            self._messages.popleft()
            self.dropped += 1

    def put_back(self, message: Message) -> None:
        """A message paho refused: first in line again."""
        self._messages.appendleft(message)

    def take(self) -> Message:
        return self._messages.popleft()

    def clear(self) -> None:
        self.dropped += len(self._messages)
        self._messages.clear()

    def __len__(self) -> int:
        return len(self._messages)


class Pipe:
    """The way to paho: retained control messages and results first (one per key,
    never dropped), then the bounded ``Outbox`` of states; at most ``WINDOW`` of them
    in paho's hands and not yet written or acknowledged.

    ``client()`` is the paho client of the connection, ``connected()`` whether there
    is one now.  paho's thread calls ``written_one`` and nothing else."""

    def __init__(self, queue_size: int, counters: Counters, peers: PeerLog,
                 client: Callable[[], paho.Client | None],
                 connected: Callable[[], bool]) -> None:
        self.outbox = Outbox(queue_size)
        # Retained control messages (status, availability, discovery) and command
        # results go before the outbox and are never dropped: one entry per key, so
        # this is bounded by the number of topics (and of commands in progress).
        self.control: dict[str, Message] = {}
        self.counters = counters
        self._peers = peers
        self._client = client
        self._connected = connected
        # Messages in paho's hands: ``_handed - counters.written``.  Each of the two
        # counters has one writer (this loop, paho's thread), so no lock is needed.
        self._handed = 0
        self.waiting_for_window = False
        self._stale: list[Message] = []  # states of before the last connect

    def written_one(self) -> bool:
        """paho wrote (or had acknowledged) a message; on paho's thread.  True when the
        loop waits for room in the window and must be woken."""
        self.counters.written += 1
        return self.waiting_for_window  # set before the loop looks at the window again

    def connected_anew(self) -> None:
        """What paho held when the last connection went is lost with it (each
        connection has a fresh client): counted, then the window starts empty.  The
        states still waiting are old news by now: set aside, before anything drains
        (the state desk takes them: ``waiting``)."""
        self.counters.lost_in_flight += self.in_window()
        self._handed = self.counters.written
        while self.outbox:
            self._stale.append(self.outbox.take())

    def empty(self) -> bool:
        return not (self.control or self.outbox or self.in_window())

    def waiting(self) -> list[Message]:
        """Takes the states set aside at the connect."""
        messages, self._stale = self._stale, []
        return messages

    def queued(self) -> int:
        return len(self.outbox) + len(self.control)

    def in_window(self) -> int:
        return max(0, self._handed - self.counters.written)

    def send(self, message: Message) -> None:
        """Queue a message and send what the window allows."""
        self.outbox.put(message)
        self.drain()

    def send_control(self, message: Message, key: str | None = None) -> None:
        """A message that must not be dropped; a newer one for the same ``key`` (its
        topic by default) replaces one still waiting."""
        self.control.pop(key or message.topic, None)
        self.control[key or message.topic] = message
        self.drain()

    def drain(self) -> None:
        """Hand paho what the window allows: control messages first, then the outbox."""
        while (self.control or self.outbox) and self._connected():
            # The flag goes up before the window is read: an on_publish in between
            # then still wakes this loop (paho's thread reads the flag).
            self.waiting_for_window = True
            if self.in_window() >= WINDOW:
                return
            self.waiting_for_window = False
            if self.control:
                key = next(iter(self.control))
                if not self._hand_to_paho(self.control[key]):
                    return
                del self.control[key]
            else:
                message = self.outbox.take()
                if not self._hand_to_paho(message):
                    self.outbox.put_back(message)
                    return
        self.waiting_for_window = False

    def _hand_to_paho(self, message: Message) -> bool:
        """True when the message is done with: handed to paho, or dropped because
        paho can never send it (it must not block the queue behind it); False when
        paho refused it for now (no connection), to be tried again."""
        client = self._client()
        assert client is not None
        try:
            info = client.publish(message.topic, message.payload, message.qos,
                                        message.retain, message.properties)
        except (ValueError, TypeError) as exc:
            self.counters.undeliverable += 1
            self._peers.warning("undeliverable", "mqtt: dropped a message to %.80r: %s",
                                message.topic, exc)
            return True
        if info.rc == MQTTErrorCode.MQTT_ERR_SUCCESS:
            if not self.in_window():  # the wait starts now
                self._progress = (self.counters.written, asyncio.get_running_loop().time())
            self._handed += 1
            self.counters.published += 1
            return True
        return False

    def publishing(self) -> bool:
        """Connected, and what was handed to paho is being written: messages in its
        hands with none written for ``STALLED_S`` mean a connection that only looks
        up (a broker that stopped reading)."""
        if not self._connected():
            return False
        now, written = asyncio.get_running_loop().time(), self.counters.written
        if written != self._progress[0]:
            self._progress = (written, now)
        if not self.in_window():
            return True
        return now - self._progress[1] < STALLED_S


class MqttClient(Frontend):
    """The gateway's MQTT connection; ``start()`` and ``stop()`` on the gateway's loop."""

    name = "mqtt"

    def __init__(self, gateway: GatewayLike, config: MqttConfig) -> None:
        super().__init__()
        self.gateway = gateway
        self.config = config
        self.topics = Topics.of(config, gateway.config.gateway_id)
        self.prefix = self.topics.prefix
        self.status_topic = self.topics.status
        self.counters = Counters()
        self._peers = PeerLog(log)
        self._client: paho.Client | None = None
        self.connected = False
        self.pipe = Pipe(config.queue_size, self.counters, self._peers,
                         lambda: self._client, lambda: self.connected)
        self.outbox = self.pipe.outbox
        # The sensors are fixed for the process's life, so their discovery configs are.
        self.discovery = discovery_configs(setup_of(gateway.config, self.topics)) \
            if config.homeassistant_discovery else {}
        self.states = StateDesk(gateway, config, self.topics, self.pipe.send,
                                self._send_control, lambda: self.connected, self.pipe.waiting)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lost = asyncio.Event()
        self._answered = asyncio.Event()  # the broker answered CONNECT (either way)
        self._runner: asyncio.Task[None] | None = None
        self._unsubscribe: Any = None
        self.sweep = RetainedSweep(
            self.topics, config.discovery_prefix if config.homeassistant_discovery else None,
            self.discovery, retained_leaves(config, gateway.sensors), self._send_control)
        self._sweep_timer: asyncio.TimerHandle | None = None
        self._stopping = False
        self._last_problem: str | None = None
        self.failover = Failover(config.brokers)
        self.identity = Identity(self.topics, self.client_id, self._send_control)
        self.desk = CommandDesk(gateway, config, self._send_control, self.counters,
                                self._peers)

    # ------------------------------------------------------------ topics

    def sensor_topic(self, sensor: str, leaf: str) -> str:
        return self.topics.sensor(sensor, leaf)

    # ------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Connect in the background (again, after ``stop``: the supervisor restarts
        a failed client this way)."""
        self._loop = asyncio.get_running_loop()
        self._stopping = False
        self.connected = False
        self.desk.cancel()
        self._unsubscribe = self.gateway.cache.subscribe(self.states.on_cache_event, self.fail)
        self._runner = asyncio.create_task(self._keep_connected(), name="mqtt")
        self.guarded(self._runner)

    @property
    def client_id(self) -> str:
        return self.config.client_id or f"imu-gateway-{self.gateway.config.gateway_id}"

    def _make_client(self, client_id: str | None = None) -> paho.Client:
        c = self.config
        v5 = c.protocol == "5"
        client = paho.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id or self.client_id,
            protocol=paho.MQTTv5 if v5 else paho.MQTTv311,
            clean_session=None if v5 else True,
            reconnect_on_failure=False,  # the reconnect is ours (see the module docstring)
        )
        if c.username is not None:
            client.username_pw_set(c.username, c.password)
        if c.tls:
            client.tls_set(ca_certs=c.ca_file, certfile=c.certfile, keyfile=c.keyfile)
        client.will_set(self.status_topic, OFFLINE, qos=CONTROL_QOS, retain=True)
        client.max_queued_messages_set(WINDOW * 2)
        client.on_connect = self._paho_connect
        client.on_disconnect = self._paho_disconnect
        client.on_publish = self._paho_publish
        client.on_message = self._paho_message
        return client

    async def stop(self) -> None:
        """Say ``offline`` (every sensor's availability, then the status), then
        disconnect.  If that is not acknowledged in time, the connection is dropped
        without DISCONNECT, so the broker publishes the last will instead."""
        self._stopping = True
        if self._unsubscribe is not None:
            self._unsubscribe()
        self.states.cancel()
        self.desk.cancel()
        said_offline = False
        if self.connected:
            self.outbox.clear()  # states of before: "offline" is the last word
            for name in self.gateway.sensors:
                self._send_control(Message(self.sensor_topic(name, "availability"), OFFLINE,
                                           CONTROL_QOS, True))
            self._send_control(Message(self.status_topic, OFFLINE, CONTROL_QOS, True))
            said_offline = await self._flushed(timeout=2.0)
        if self._runner is not None:
            self._runner.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._runner
        client = self._client
        if client is not None:
            if said_offline:
                client.disconnect()
            await asyncio.to_thread(client.loop_stop)
            _close_sockets(client)

    async def _flushed(self, timeout: float) -> bool:
        """Wait until everything queued was written or acknowledged."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while self.connected and loop.time() < deadline:
            self.pipe.drain()
            if self.pipe.empty():
                return True
            await asyncio.sleep(0.01)
        return False

    async def _keep_connected(self) -> None:
        """Connect, and again whenever the connection is lost or fails: to the next
        broker of the list, after the wait ``Failover`` says."""
        while True:
            worked = await self._connection(self.failover.current)
            self.connected = False
            wait = self.failover.ended(worked)
            if self.identity.held_off:  # another gateway holds this id: look again later
                self.identity.held_off, wait = False, max(wait, mqtt_identity.RIVAL_WAIT)
            if wait:
                await asyncio.sleep(wait)

    async def _connection(self, broker: Broker) -> bool:
        """One connection to ``broker``, until it is lost; True when it worked."""
        self._lost.clear()
        connects = self.counters.connects
        try:
            if await self.identity.rival(broker, self._make_client) is not None:
                return False
        except BrokerUnreached as failed:  # this broker's try: the connect would fail too
            self._problem(self._unreached(broker, failed.kind, failed.detail))
            return False
        # A new paho client for every connection (the session is clean anyway, and the
        # last will is set on each, so it works on whichever broker this is): paho's
        # loop_start() makes a new wake-up socket pair each time without closing the
        # last; each client's sockets are closed when it is done.
        self._client = client = self._make_client()
        try:
            await asyncio.to_thread(client.connect, broker.host, broker.port, KEEPALIVE_S)
        except (OSError, ValueError) as exc:
            self._problem(self._unreached(broker, "unreachable", reason_of(exc)))
            _close_sockets(client)
            return False
        self._answered.clear()
        client.loop_start()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._answered.wait(), CONNACK_TIMEOUT)
        if self._answered.is_set():
            await self._lost.wait()
        else:
            self._problem(self._unreached(broker, "silent"))
        await asyncio.to_thread(client.loop_stop)
        _close_sockets(client)
        return self.counters.connects > connects

    def _problem(self, text: str) -> None:
        """Log a connection problem once, until it changes or a connection works."""
        if text != self._last_problem:
            log.warning("mqtt: %s; retrying", text)
            self._last_problem = text

    # ------------------------------------------------------------ paho's thread

    def _hand_over(self, fn: Any, *args: Any) -> None:
        assert self._loop is not None
        with contextlib.suppress(RuntimeError):  # the loop closed during shutdown
            self._loop.call_soon_threadsafe(self._guard, fn, *args)

    def _guard(self, fn: Any, *args: Any) -> None:
        """Run a handed-over event; a failure is this client's, for its supervisor."""
        try:
            fn(*args)
        except Exception as exc:  # the supervisor logs and restarts
            self.fail(exc)

    def _paho_connect(self, client: paho.Client, userdata: Any, flags: Any,
                      reason: ReasonCode, properties: Properties | None) -> None:
        self._hand_over(self._on_connect, reason)

    def _paho_disconnect(self, client: paho.Client, userdata: Any, flags: Any,
                         reason: ReasonCode, properties: Properties | None) -> None:
        self._hand_over(self._on_disconnect, reason)

    def _paho_publish(self, client: paho.Client, userdata: Any, mid: int,
                      reason: ReasonCode, properties: Properties | None) -> None:
        if self.pipe.written_one():
            self._hand_over(self.pipe.drain)

    def _paho_message(self, client: paho.Client, userdata: Any,
                      message: paho.MQTTMessage) -> None:
        self._hand_over(self._on_message, message)

    # ------------------------------------------------------------ connection events

    def _on_connect(self, reason: ReasonCode) -> None:
        self._answered.set()
        if reason.is_failure:
            self._problem(f"the broker at {self.failover.current} refused the connection: "
                          f"{reason}")
            self._lost.set()
            return
        self.connected = True
        self.counters.connects += 1
        self._last_problem = None
        self.pipe.connected_anew()
        log.info("mqtt: connected to %s (MQTT %s)", self.failover.current, self.config.protocol)
        self._subscribe()
        self._announce()

    def _on_disconnect(self, reason: ReasonCode) -> None:
        if self.connected and not self._stopping:
            log.warning("mqtt: connection to %s lost (%s); reconnecting",
                        self.failover.current, reason)
        elif not self._answered.is_set() and not self._stopping:
            self._problem(self._unreached(self.failover.current, "closed"))
        self._answered.set()
        self.connected = False
        self._lost.set()

    def _unreached(self, broker: Broker, kind: str, detail: str = "") -> str:
        """Why ``broker`` was not reached, the same from the probe and the connect."""
        hint = "" if self.config.tls else " (a TLS port? then use mqtts://)"
        if kind == "unreachable":
            return f"cannot connect to {broker}: {detail}"
        if kind == "silent":
            return f"no answer from {broker} within {CONNACK_TIMEOUT:g} s of connecting{hint}"
        return f"{broker} closed the connection without answering{hint}"

    def _subscribe(self) -> None:
        assert self._client is not None
        for topic in self.identity.claim_topics:  # a rival's claim, live (QoS 0: as probe)
            self._client.subscribe(topic, qos=0)
        if self.config.allow_commands:
            # MQTT 5: the retain flag as published, so that a retained command is
            # known as one even when it arrives live (3.1.1 brokers clear the flag).
            topic = f"{self.prefix}/+/cmd/+"
            if self.config.protocol == "5":
                self._client.subscribe(topic, options=SubscribeOptions(
                    qos=1, retainAsPublished=True))
            else:
                self._client.subscribe(topic, qos=1)
        assert self._loop is not None
        self.sweep.start(self._client, self._loop.time())
        if self._sweep_timer is not None:  # an earlier connection's
            self._sweep_timer.cancel()
        self._sweep_timer = self._loop.call_later(SWEEP_S, self._end_sweep)

    def _end_sweep(self) -> None:
        if self._client is not None and self.connected:
            self.sweep.end(self._client)

    def _announce(self) -> None:
        """Everything retained, anew: after every connect.  The control messages go
        first; then each sensor's latest state (the states that waited are old news by
        now: ``Pipe.connected_anew``)."""
        self.identity.claim_it()
        self._send_control(Message(self.status_topic, ONLINE, CONTROL_QOS, True))
        described = json_properties(self.config)  # one for all (paho packs it per send)
        for topic, payload in self.discovery.items():
            self._send_control(Message(topic, json_bytes(payload), CONTROL_QOS, True,
                                       described))
        self.states.announce()

    # ------------------------------------------------------------ incoming

    def _on_message(self, message: paho.MQTTMessage) -> None:
        topic = message.topic
        parts = topic.removeprefix(f"{self.prefix}/").split("/")
        if topic.startswith(self.prefix + "/") and len(parts) == 3 and parts[1] == "cmd":
            self.desk.take(message, parts[0], parts[2])
        elif topic in self.identity.claim_topics:
            if self.identity.seen(message) and self._client is not None:
                self._client.disconnect()  # cleanly: no will, the status stays theirs
        elif self._loop is not None:
            self.sweep.take(message, self._loop.time())

    # ------------------------------------------------------------ stats

    @property
    def publishing(self) -> bool:
        return self.pipe.publishing()

    def _send_control(self, message: Message, key: str | None = None) -> None:
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


def _close_sockets(client: paho.Client) -> None:
    """paho 2.2 leaves the socket of a failed or lost connection, and loop_start()'s
    wake-up socket pair, to the garbage collector; ``_reset_sockets`` (private, but the
    one place that closes all three) closes them now."""
    with contextlib.suppress(OSError):
        client._reset_sockets()

