"""One MQTT session kept up: connect to the brokers of ``mqtt.url`` in turn, with a
back-off (``failover.py``), and again whenever the connection is lost.

Two front ends use it, each with a session (a client id and a last will) of its own:
the plain topics (``frontends/mqtt``: will = status ``offline``) and Sparkplug B
(``frontends/sparkplug``: will = NDEATH, whose ``bdSeq`` changes with every connection).

Threads.  None of paho's: its network loop is the gateway's event loop
(``driver.py``), so paho's callbacks, and everything here, run on the loop.  Only the
blocking connect (DNS, TCP, TLS, CONNECT) runs in the loop's executor, before the
socket is handed to the loop.

Connecting.  The connect itself (TCP, TLS, CONNECT) is ours, in an executor: paho's
own automatic reconnect swallows the reason a connection failed, and a user looking
at a TLS or password problem needs that reason.  Each distinct failure is logged once;
the retries after it are quiet, and "connected" is logged on the way back.  A new paho
client serves each connection (the session is clean anyway, and the will is set on
each, so it works on whichever broker this is).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.properties import Properties
from paho.mqtt.reasoncodes import ReasonCode

from ..config import Broker, MqttConfig
from ..supervise import PeerLog
from .driver import Driver, close_sockets
from .errors import BrokerUnreached
from .failover import Failover
from .message import Counters, Message
from .pipe import KEEPALIVE_S, WINDOW, Pipe
from .probe import PROBE_TIMEOUT, reason_of

#: a broker that says nothing after CONNECT (a TLS port, say); the probe's wait too
CONNACK_TIMEOUT = PROBE_TIMEOUT


class Ready(NamedTuple):
    """The owner's word before a connect."""

    broker: Broker  # the broker to connect to
    stay_away: float | None  # None: connect now; else stay away this many seconds


class Owner(Protocol):
    """What a session asks of the front end it serves; all on the event loop."""

    async def before_connect(self, brokers: tuple[Broker, ...]) -> Ready:
        """Which of ``brokers`` (the list, from the one whose turn it is) to connect
        to, and whether to stay away instead.  Raises ``BrokerUnreached`` (the try of
        the first failed)."""

    def will(self) -> Message:
        """The last will of the next connection: asked before each try, whether or not
        its CONNECT goes out (the session's ``connect_sent`` is told when it does)."""

    def on_connected(self) -> None:
        """CONNACK came: subscribe, publish everything retained anew."""

    def on_message(self, message: paho.MQTTMessage) -> None: ...

    def fail(self, exc: BaseException) -> None:
        """A bug in a handed-over event: the front end's supervisor restarts it."""


class Session:
    """One client id's connection, kept up; ``pipe`` publishes on it."""

    def __init__(self, config: MqttConfig, client_id: str, owner: Owner,
                 log: logging.Logger, queue_size: int,
                 connect_sent: Callable[[], None] = lambda: None) -> None:
        """``connect_sent``: called on the event loop each time a CONNECT packet (with
        the owner's last will) went out; a try the broker refused at TCP sends none.
        (Sparkplug counts them: the will's bdSeq.)"""
        self.config, self.client_id, self.owner, self.log = config, client_id, owner, log
        self.connect_sent = connect_sent
        self.counters = Counters()
        self.peers = PeerLog(log)
        self.client: paho.Client | None = None
        self._driver: Driver | None = None  # the client's network loop, while connected
        self.connected = False
        self.stopping = False
        self.pipe = Pipe(queue_size, self.counters, self.peers,
                         lambda: self.client, lambda: self.connected)
        self.failover = Failover(config.brokers)
        self._lost = asyncio.Event()
        self._answered = asyncio.Event()  # the broker answered CONNECT (either way)
        self._last_problem: str | None = None
        #: the subscriptions (their message ids) the broker has granted on this connection
        self.granted: set[int] = set()

    def run(self) -> asyncio.Task[None]:
        """Connect in the background, for as long as the task runs."""
        self.stopping = False
        self.connected = False
        return asyncio.create_task(self._keep_connected(), name=f"mqtt {self.client_id}")

    def make_client(self, client_id: str | None = None) -> paho.Client:
        """A paho client set up as this session's (TLS, credentials, callbacks), with
        no will yet."""
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
        client.max_queued_messages_set(WINDOW * 2)
        client.on_connect = self._paho_connect
        client.on_disconnect = self._paho_disconnect
        client.on_message = self._paho_message
        client.on_subscribe = self._paho_subscribe
        return client

    async def stop(self, runner: asyncio.Task[None] | None, last_words: list[Message]) -> None:
        """Send ``last_words``, then disconnect.  If they are not acknowledged in time,
        the connection is dropped without DISCONNECT, so the broker publishes the
        last will instead."""
        self.stopping = True
        said = False
        if self.connected:
            self.pipe.outbox.clear()  # what waited is old: the last words go last
            for message in last_words:
                self.pipe.send_control(message)
            said = await self.flushed(timeout=2.0)
        if runner is not None:
            runner.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await runner
        client, driver = self.client, self._driver
        if client is not None:
            if said:
                client.disconnect()  # (written by close(), at once)
            if driver is not None and driver.client is client:
                driver.close()
            else:
                close_sockets(client)
        self.connected = False

    async def flushed(self, timeout: float) -> bool:
        """Wait until everything queued was written or acknowledged."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while loop.time() < deadline and self.connected:  # (lost: nothing more goes out)
            self.pipe.drain()
            if self.pipe.empty():
                return True
            await asyncio.sleep(0.01)
        return False

    async def _keep_connected(self) -> None:
        """Connect, and again whenever the connection is lost or fails: to the next
        broker of the list, after the wait ``Failover`` says."""
        while True:
            stay_away = None
            try:
                # the first try goes to the first broker alone; a reconnect takes the
                # first broker of the list that answers (a cluster's nodes do not come
                # back from a node's loss at the same moment)
                again = self.counters.connects or self.failover.failures
                brokers = self.failover.order() if again else (self.failover.current,)
                broker, stay_away = await self.owner.before_connect(brokers)
                self.failover.move_to(broker)
                worked = stay_away is None and await self._connection(broker)
            except BrokerUnreached as failed:  # its try: the connect would fail too
                self._problem(self._unreached(failed.broker or self.failover.current,
                                              failed.kind, failed.detail))
                worked = False
            self.connected = False
            wait = self.failover.ended(worked)
            if stay_away is not None:
                wait = max(wait, stay_away)
            if wait:
                await asyncio.sleep(wait)

    async def _connection(self, broker: Broker) -> bool:
        """One connection to ``broker``, until it is lost; True when it worked."""
        self._lost.clear()
        connects = self.counters.connects
        # each client's socket is closed when it is done (paho leaves a failed
        # connect's to the garbage collector)
        self.client = client = self.make_client()
        will = self.owner.will()
        client.will_set(will.topic, will.payload, will.qos, will.retain)
        try:
            await asyncio.to_thread(client.connect, broker.host, broker.port, KEEPALIVE_S)
        except (OSError, ValueError) as exc:
            self._problem(self._unreached(broker, "unreachable", reason_of(exc)))
            close_sockets(client)
            return False
        # paho's connect() returns once it has written the CONNECT (no write callback
        # is set yet, so it writes it itself)
        self.connect_sent()
        self._answered.clear()
        self._driver = driver = Driver(client, lambda: self._guard(self.pipe.settle))
        driver.attach()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._answered.wait(), CONNACK_TIMEOUT)
        if self._answered.is_set():
            await self._lost.wait()
        else:
            self._problem(self._unreached(broker, "silent"))
            self.client = None  # (no answer can come now: its socket is closed next)
        driver.close()
        return self.counters.connects > connects

    def _problem(self, text: str) -> None:
        """Log a connection problem once, until it changes or a connection works."""
        if text != self._last_problem:
            self.log.warning("mqtt: %s; retrying", text)
            self._last_problem = text

    def _unreached(self, broker: Broker, kind: str, detail: str = "") -> str:
        """Why ``broker`` was not reached, the same from a probe and the connect."""
        hint = "" if self.config.tls else " (a TLS port? then use mqtts://)"
        if kind == "unreachable":
            return f"cannot connect to {broker}: {detail}"
        if kind == "silent":
            return f"no answer from {broker} within {CONNACK_TIMEOUT:g} s of connecting{hint}"
        return f"{broker} closed the connection without answering{hint}"

    # ------------------------------------------------------------ paho's callbacks
    # (on the event loop, inside the driver's loop_read, loop_write or loop_misc)

    def _guard(self, fn: Callable[..., None], *args: Any) -> None:
        """Run an event; a failure is the owner's, for its supervisor (not paho's,
        which would pass it up through the driver to the event loop's log)."""
        try:
            fn(*args)
        except Exception as exc:  # the supervisor logs and restarts
            self.owner.fail(exc)

    def _paho_connect(self, client: paho.Client, userdata: Any, flags: Any,
                      reason: ReasonCode, properties: Properties | None) -> None:
        self._guard(self._on_connect, reason, client)

    def _paho_disconnect(self, client: paho.Client, userdata: Any, flags: Any,
                         reason: ReasonCode, properties: Properties | None) -> None:
        self._guard(self._on_disconnect, reason, client)

    def _paho_message(self, client: paho.Client, userdata: Any,
                      message: paho.MQTTMessage) -> None:
        self._guard(self.owner.on_message, message)

    def _paho_subscribe(self, client: paho.Client, userdata: Any, mid: int,
                        reasons: list[ReasonCode], properties: Properties | None) -> None:
        if reasons and not any(r.is_failure for r in reasons):
            self._guard(self.granted.add, mid)

    # ------------------------------------------------------------ connection events

    def _on_connect(self, reason: ReasonCode, client: paho.Client) -> None:
        if client is not self.client or self.stopping:
            return  # a connection given up on (no answer in time), or the end: not ours
        self._answered.set()
        if reason.is_failure:
            self._problem(f"the broker at {self.failover.current} refused the connection: "
                          f"{reason}")
            self._lost.set()
            return
        self.connected = True
        self.granted.clear()  # an earlier connection's
        self.counters.connects += 1
        self._last_problem = None
        self.pipe.connected_anew()
        self.log.info("mqtt: connected to %s (MQTT %s)", self.failover.current,
                      self.config.protocol)
        self.owner.on_connected()

    def _on_disconnect(self, reason: ReasonCode, client: paho.Client) -> None:
        if client is not self.client:
            return  # an earlier connection's: this one is not lost
        if self.connected and not self.stopping:
            self.log.warning("mqtt: connection to %s lost (%s); reconnecting",
                             self.failover.current, reason)
        elif not self._answered.is_set() and not self.stopping:
            self._problem(self._unreached(self.failover.current, "closed"))
        self._answered.set()
        self.connected = False
        self._lost.set()
