"""One gateway per ``gateway_id`` on a broker: the second says so and stays away.

Two gateways with one ``gateway_id`` would overwrite each other's retained messages,
and with one client id the broker would hand the session from one to the other at
every reconnect.  So each gateway process claims its id: a retained message on
``{base}/{gw}/instance`` names the process (a random instance id, host, pid, start
time), published before its status.

* **Before connecting** (with its real client id, which would take over a running
  gateway's session), the gateway connects a probe with a client id of its own, reads
  the retained status and claim, and sends itself an echo to know it has them.  A
  claim by another instance while the status is ``online`` is a live gateway of that
  id: this one logs who it is and does not connect; it looks again later (the other
  may go, and its will then says ``offline``).  Its own predecessor (same host, its
  pid gone: a crash and a restart faster than the broker's keep-alive notices) is
  not a rival.
* **While connected,** it listens to its claim topic: another instance's claim means
  two came up at once.  The earlier start keeps the id; the later one says so and
  disconnects cleanly (no will: the status stays the other's ``online``).
* **The client id** is claimed the same way, on ``{base}/_clients/{client_id}``: a
  gateway of another ``gateway_id`` set to the same ``client_id`` is found by the probe
  (the claim names its gateway, whose status and claim the probe then reads).
  (mosquitto 2.0 closes a taken-over connection without saying why, so the probe is
  the only reliable signal.)
* **A probe that cannot reach the broker** (no TCP connection, no CONNACK in time, or
  closed unanswered) counts as this broker's failed try: the real connect would fail
  the same way, and a cluster node that holds connections for seconds while it
  recovers would otherwise cost that wait twice.  On a reconnect the probe is hedged
  across the broker list (``read_retained_hedged``), and what it read tells the
  front end which retained messages the broker already serves.  A probe the broker
  refuses, or one whose echo does not come back (an ACL, say), leaves the decision
  to the real connect: the probe's client id and topic are not the gateway's.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import NamedTuple

import paho.mqtt.client as paho
from paho.mqtt.enums import MQTTErrorCode
from paho.mqtt.reasoncodes import ReasonCode

from ..config import Broker
from ..errors import BrokerUnreached, ProbeFailed
from .mqtt_topics import CONTROL_QOS, Message, Topics

log = logging.getLogger("imu_gateway.mqtt")

#: How long a gateway that found its id (or client id) in use waits before it looks again.
RIVAL_WAIT = 30.0
#: How long the probe waits for the broker (connect, retained messages, its echo).
PROBE_TIMEOUT = 5.0
#: A probe not answered after HEDGE_S gets another beside it, up to HEDGE_MAX at once
#: (``read_retained_hedged``).
HEDGE_S, HEDGE_MAX = 0.5, 8
#: The largest pid Linux gives (``pid_max`` at most 2**22), and the latest start a
#: claim may carry (the year 9999): anything past them is a malformed claim.
MAX_PID, MAX_STARTED = 2**22, 253402300799.0


@dataclass(frozen=True, slots=True)
class Claim:
    """Who holds a ``gateway_id``: one gateway process."""

    instance: str
    host: str
    pid: int
    started: float  # Unix time
    gateway_id: str
    client_id: str

    @classmethod
    def mine(cls, gateway_id: str, client_id: str) -> Claim:
        return cls(uuid.uuid4().hex, socket.gethostname(), os.getpid(), round(time.time(), 3),
                   gateway_id, client_id)

    def payload(self) -> bytes:
        return json.dumps(asdict(self)).encode()

    @classmethod
    def parse(cls, payload: bytes) -> Claim | None:
        """A claim from its payload; None for anything else (an empty retained message
        clears the topic; a malformed one is nobody's)."""
        try:
            data = json.loads(payload)
            claim = cls(str(data["instance"]), str(data["host"]), int(data["pid"]),
                        float(data["started"]), str(data["gateway_id"]),
                        str(data["client_id"]))
        except (ValueError, KeyError, TypeError, ArithmeticError):  # 1e400, Infinity
            return None
        # Anyone with publish rights may write these topics: values a process or a
        # clock cannot have are nobody's too (a pid past the kernel's, a NaN start).
        if not (0 < claim.pid <= MAX_PID and 0 <= claim.started <= MAX_STARTED):
            return None
        return claim

    def describe(self) -> str:
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(self.started))
        return f"host {self.host}, pid {self.pid}, since {since}"

    def first(self, other: Claim) -> bool:
        """Whether this claim came before ``other`` (the earlier start keeps the id)."""
        return (self.started, self.instance) < (other.started, other.instance)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's process
    return True


def live_rival(mine: Claim, status: str | None, theirs: Claim | None,
               alive: Callable[[int], bool] = pid_alive) -> Claim | None:
    """The other gateway holding this id now, if there is one."""
    if theirs is None or theirs.instance == mine.instance or status != "online":
        return None
    if theirs.host == mine.host and not alive(theirs.pid):
        return None  # this machine's gateway before a restart; its will is late
    # (A container's gateway is pid 1 after every restart, so a crashed predecessor
    # looks alive: the gateway then waits for its will, RIVAL_WAIT at a time.  Taking
    # the same pid for a predecessor would let two host-networked containers, both
    # pid 1 on one host name, take each other's session: the wait is the safe side.)
    return theirs


class Progress:
    """How far a probe has come: its TCP (and TLS) connection is up (``reached``), the
    broker answered its CONNECT (``answered``)."""

    def __init__(self) -> None:
        self.reached, self.answered = asyncio.Event(), asyncio.Event()


async def read_retained(make: Callable[[str], paho.Client], broker: Broker, client_id: str,
                        topics: list[str], timeout: float = PROBE_TIMEOUT,
                        progress: Progress | None = None) -> dict[str, bytes]:
    """The retained message of each of ``topics`` on ``broker`` (those that have one),
    read by a connection of its own: ``make(client_id)`` gives a client set up as the
    gateway's (TLS, credentials).  An echo sent after the subscription tells when the
    retained messages are all in.  Raises ``BrokerUnreached`` when the broker was not
    reached, ``ConnectionRefusedError`` when it refused the probe, ``TimeoutError``
    when it answered the connect but not the rest.  ``progress`` tells how far the
    probe has come."""
    loop = asyncio.get_running_loop()
    echo = f"{topics[0]}/probe/{uuid.uuid4().hex}"
    seen: dict[str, bytes] = {}
    done: asyncio.Future[object] = loop.create_future()
    client = make(client_id)
    acked: list[bool] = []  # the broker answered the connect (set on paho's thread)

    def settle(result: object) -> None:
        if not done.done():
            done.set_result(result)

    def on_connect(c: paho.Client, u: object, f: object, reason: ReasonCode,
                   p: object) -> None:
        acked.append(True)
        if progress is not None:
            loop.call_soon_threadsafe(progress.answered.set)
        if reason.is_failure:
            loop.call_soon_threadsafe(settle, ConnectionRefusedError(str(reason)))
        else:
            # QoS 0: a read of retained messages needs no more, and NATS's MQTT makes a
            # JetStream consumer for every QoS 1 subscription (slow while a node is down)
            c.subscribe([(topic, 0) for topic in (*topics, echo)])

    def on_message(c: paho.Client, u: object, message: paho.MQTTMessage) -> None:
        if message.topic == echo:  # after the retained ones: all are in
            loop.call_soon_threadsafe(settle, None)
        elif message.retain:
            seen[message.topic] = bytes(message.payload)

    def on_disconnect(c: paho.Client, u: object, f: object, reason: object,
                      p: object) -> None:
        if not acked:
            loop.call_soon_threadsafe(settle, BrokerUnreached("closed"))

    # (the gateway's own callbacks, which ``make`` set, are not the probe's)
    client.on_connect, client.on_message = on_connect, on_message
    client.on_subscribe = lambda c, *_: c.publish(echo, b"", qos=0)
    client.on_disconnect, client.on_publish = on_disconnect, None
    client.will_clear()  # the gateway's will is not the probe's to leave
    # (shielded: a probe given up on while it connects, a hedge that lost, must not
    # wait for the connect, and what the connect opens is closed when it ends)
    connecting = asyncio.ensure_future(
        asyncio.to_thread(client.connect, broker.host, broker.port, 10))
    try:
        try:
            await asyncio.shield(connecting)
        except (OSError, ValueError) as exc:
            raise BrokerUnreached("unreachable", reason_of(exc)) from exc
        if progress is not None:
            progress.reached.set()
        client.loop_start()
        try:
            result = await asyncio.wait_for(done, timeout)
        except TimeoutError:
            if not acked:
                raise BrokerUnreached("silent") from None
            raise
        if isinstance(result, Exception):
            raise result
        return seen
    finally:
        if connecting.done():
            with contextlib.suppress(Exception):
                client.disconnect()
            await asyncio.to_thread(client.loop_stop)
            close_sockets(client)
        else:
            connecting.add_done_callback(lambda ended: _closed_late(client, ended))


def close_sockets(client: paho.Client) -> None:
    """paho 2.2 leaves the socket of a failed or lost connection, and loop_start()'s
    wake-up socket pair, to the garbage collector; ``_reset_sockets`` (private, but the
    one place that closes all three) closes them now."""
    with contextlib.suppress(OSError):
        client._reset_sockets()


def _closed_late(client: paho.Client, connect: asyncio.Future[MQTTErrorCode]) -> None:
    """The connect of a probe given up on has ended: what it opened is closed (and its
    failure, if it failed, is of no interest)."""
    if not connect.cancelled():
        connect.exception()
    close_sockets(client)


async def read_retained_hedged(make: Callable[[str], paho.Client], brokers: Sequence[Broker],
                               client_id: str, topics: list[str]
                               ) -> tuple[Broker, dict[str, bytes]]:
    """``read_retained`` from the first of ``brokers`` to answer, hedged: while a probe
    is out and none has finished, another starts every ``HEDGE_S`` on the next broker
    of the list in turn (the same one, when the list has one; client id
    ``{client_id}-{n}``), up to ``HEDGE_MAX`` at once and ``PROBE_TIMEOUT`` in all.
    The first probe to finish wins; the rest are closed.

    Why: a NATS node whose JetStream groups are electing new leaders (a node of the
    cluster was lost) holds each new MQTT connection 4 s and then closes it unanswered,
    even when the leaders are back meanwhile, and the surviving nodes do not recover
    at the same moment.  One probe at a time meets the recovery up to 4 s late, on one
    node; probes every ``HEDGE_S`` meet it within that, on the first node that is back
    (docs/scaling.md).

    When no probe is out any more (each failed: a broker that closes at once, or
    refuses the TCP connection) the last failure is raised, ``BrokerUnreached`` naming
    its broker.  A refusal of the connect, or an answer without the retained messages,
    raises ``ProbeFailed`` at once.  When the time is up: ``ProbeFailed`` for a broker
    that answered the connect but not the rest (the real connect decides there), else
    ``BrokerUnreached("silent")`` naming a broker that said nothing.  A broker
    whose probe is still opening its TCP connection (a host that drops the SYN) gets
    no other meanwhile: each waits on a thread of the loop's executor."""
    loop = asyncio.get_running_loop()
    deadline = next_start = loop.time()
    deadline += PROBE_TIMEOUT
    turn, cursor = list(brokers), 0  # (the next broker: the first in turn from cursor)
    pending: dict[asyncio.Task[dict[str, bytes]], tuple[Broker, Progress]] = {}
    started = 0
    try:
        while (now := loop.time()) < deadline:
            opening = {b for b, p in pending.values() if not p.reached.is_set()}
            free = [b for k in range(len(brokers))
                    if (b := brokers[(cursor + k) % len(brokers)]) in turn
                    and b not in opening]
            if now >= next_start and free and len(pending) < HEDGE_MAX:
                nth, progress = client_id if not started else f"{client_id}-{started}", \
                    Progress()
                pending[asyncio.create_task(read_retained(
                    make, free[0], nth, topics, deadline - now, progress))] = \
                    (free[0], progress)
                cursor = brokers.index(free[0]) + 1
                started, next_start = started + 1, now + HEDGE_S
            done, _ = await asyncio.wait(pending, timeout=min(HEDGE_S, deadline - now),
                                         return_when=asyncio.FIRST_COMPLETED)
            # (a success first, of those that finished together)
            for task in sorted(done, key=lambda t: t.exception() is not None):
                broker, _ = pending.pop(task)
                if (exc := task.exception()) is None:
                    return broker, task.result()
                if not isinstance(exc, BrokerUnreached):
                    raise ProbeFailed(broker, exc) if isinstance(
                        exc, OSError | TimeoutError | ValueError) else exc
                if exc.kind == "unreachable" and broker in turn:
                    turn.remove(broker)
                if not pending:  # every probe failed: so has this try
                    raise BrokerUnreached(exc.kind, exc.detail, broker)
        # the time is up: a broker that answered, then not all the way (its echo
        # blocked by an ACL, say), is left to the real connect; else it was silence
        for broker, progress in pending.values():
            if progress.answered.is_set():
                raise ProbeFailed(broker, TimeoutError("answered, but not the rest"))
        raise BrokerUnreached("silent", broker=next(iter(pending.values()))[0])
    finally:
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)  # each closes its socket


class Probed(NamedTuple):
    """What the probe before a connect found."""

    broker: Broker  # the broker that answered first: the connect goes there
    rival: Claim | None  # another live gateway holding this id there
    served: dict[str, bytes]  # the retained messages it serves now, of those asked for


class Identity:
    """This gateway's claim on its ``gateway_id``, and what it does about rivals."""

    def __init__(self, topics: Topics, client_id: str,
                 send_control: Callable[[Message], None]) -> None:
        self.topics, self.client_id, self.send_control = topics, client_id, send_control
        self.claim = Claim.mine(topics.gateway_id, client_id)
        self.held_off = False  # a rival was found: the next connect waits RIVAL_WAIT
        self._reported: str | None = None

    def _report(self, text: str) -> None:
        """An error once per rival (the retries after it are quiet)."""
        if text != self._reported:
            log.error("mqtt: %s", text)
            self._reported = text

    async def rival(self, brokers: Sequence[Broker], make: Callable[[str], paho.Client],
                    also: Sequence[str] = ()) -> Probed:
        """Asked before connecting: the first of ``brokers`` to answer, and a live
        gateway holding this ``gateway_id`` or client id there; with the retained
        messages it serves on this gateway's topics and on ``also``.  Raises
        ``BrokerUnreached`` when no broker was reached."""
        probe_id = self.probe_id
        t = self.topics
        try:
            broker, found = await read_retained_hedged(
                make, brokers, probe_id, [t.status, t.instance, t.client(self.client_id), *also])
        except ProbeFailed as failed:  # the real connect goes there, and says why
            return Probed(failed.broker, None, {})
        served = dict(found)
        try:
            rival = live_rival(self.claim, _text(found.get(t.status)),
                               Claim.parse(found.get(t.instance, b"")))
            what = f"gateway_id {t.gateway_id!r}"
            other = Claim.parse(found.get(t.client(self.client_id), b""))
            if rival is None and other is not None and other.gateway_id != t.gateway_id:
                # the client id is claimed by a gateway of another id: is it running?
                theirs = t.of_gateway(other.gateway_id)
                # (a client id of its own: a hedge that lost may still be connecting)
                try:
                    found = await read_retained(make, broker, f"{probe_id}-c",
                                                [theirs.status, theirs.instance])
                except BrokerUnreached as failed:
                    raise BrokerUnreached(failed.kind, failed.detail, broker) from failed
                live = live_rival(self.claim, _text(found.get(theirs.status)),
                                  Claim.parse(found.get(theirs.instance, b"")))
                rival = live if live == other else None
                what = f"the client id {self.client_id!r}"
        except (OSError, TimeoutError, ValueError):
            # refused or half-answered: the real connect tries, and says why
            return Probed(broker, None, {})
        if rival is not None:
            self.held_off = True
            self._report(
                f"{what} is in use on {broker} by another gateway ({rival.describe()}); "
                f"this one stays away so as not to take its session or overwrite its "
                f"retained messages, and looks again every {RIVAL_WAIT:g} s. Give each "
                f"gateway its own gateway_id and client_id (docs/scaling.md)")
        return Probed(broker, rival, served)

    @property
    def probe_id(self) -> str:
        """The client id of this gateway's probes (its own: a probe must not take the
        gateway's session)."""
        return f"{self.client_id}-probe-{self.claim.instance[:8]}"

    @property
    def claim_topics(self) -> tuple[str, str]:
        return self.topics.instance, self.topics.client(self.client_id)

    def claim_it(self) -> None:
        for topic in self.claim_topics:
            self.send_control(Message(topic, self.claim.payload(), CONTROL_QOS, True))

    def seen(self, message: paho.MQTTMessage) -> bool:
        """A claim on this id came in while connected; True when this gateway must
        give way (another instance that started first)."""
        if message.retain:
            return False  # stored before this connection: the probe has judged it
        theirs = Claim.parse(bytes(message.payload))
        if theirs is None or theirs.instance == self.claim.instance:
            return False
        if self.claim.first(theirs):
            log.warning("mqtt: another gateway (%s) claimed gateway_id %r or client id %r "
                        "after this one; this one keeps them and publishes its claim again",
                        theirs.describe(), self.topics.gateway_id, self.client_id)
            self.claim_it()
            return False
        self.held_off = True
        self._report(f"gateway_id {self.topics.gateway_id!r} or client id {self.client_id!r} "
                     f"was claimed by another gateway that started first "
                     f"({theirs.describe()}); this one disconnects and looks again every "
                     f"{RIVAL_WAIT:g} s. Give each gateway its own gateway_id and client_id "
                     f"(docs/scaling.md)")
        return True


def _text(payload: bytes | None) -> str | None:
    return None if payload is None else payload.decode(errors="replace")


def reason_of(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
