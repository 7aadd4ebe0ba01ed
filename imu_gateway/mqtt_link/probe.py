"""The probe before a connect: a connection of its own that reads retained messages.

Before the gateway connects with its real client id (which would take over a running
gateway's session), the MQTT front end reads its claims with a probe
(``frontends/mqtt/identity.py`` says what it looks for and why).  This module is the
transport of that read: a paho client with a client id of its own subscribes to the
topics asked for, sends itself an echo to know the retained messages are all in, and
closes.

A probe that cannot reach the broker (no TCP connection, no CONNACK in time, or
closed unanswered) counts as this broker's failed try: the real connect would fail
the same way, and a cluster node that holds connections for seconds while it
recovers would otherwise cost that wait twice.  On a reconnect the probe is hedged
across the broker list (``read_retained_hedged``), and what it read tells the
front end which retained messages the broker already serves.  A probe the broker
refuses, or one whose echo does not come back (an ACL, say), leaves the decision
to the real connect: the probe's client id and topic are not the gateway's.

Like the session's, the probe's paho client runs on the event loop (``driver.py``):
its connect in the executor, the rest on the loop, callbacks included.
"""

from __future__ import annotations

import asyncio
import contextlib
import uuid
from collections.abc import Callable, Sequence

import paho.mqtt.client as paho
from paho.mqtt.enums import MQTTErrorCode
from paho.mqtt.reasoncodes import ReasonCode

from ..config import Broker
from .driver import Driver, close_sockets
from .errors import BrokerUnreached, ProbeFailed

#: How long the probe waits for the broker (connect, retained messages, its echo).
PROBE_TIMEOUT = 5.0
#: A probe not answered after HEDGE_S gets another beside it, up to HEDGE_MAX at once
#: (``read_retained_hedged``).
HEDGE_S, HEDGE_MAX = 0.5, 8


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
    acked: list[bool] = []  # the broker answered the connect

    def settle(result: object) -> None:
        if not done.done():
            done.set_result(result)

    def on_connect(c: paho.Client, u: object, f: object, reason: ReasonCode,
                   p: object) -> None:
        acked.append(True)
        if progress is not None:
            progress.answered.set()
        if reason.is_failure:
            settle(ConnectionRefusedError(str(reason)))
        else:
            # QoS 0: a read of retained messages needs no more, and NATS's MQTT makes a
            # JetStream consumer for every QoS 1 subscription (slow while a node is down)
            c.subscribe([(topic, 0) for topic in (*topics, echo)])

    def on_message(c: paho.Client, u: object, message: paho.MQTTMessage) -> None:
        if message.topic == echo:  # after the retained ones: all are in
            settle(None)
        elif message.retain:
            seen[message.topic] = bytes(message.payload)

    def on_disconnect(c: paho.Client, u: object, f: object, reason: object,
                      p: object) -> None:
        if not acked:
            settle(BrokerUnreached("closed"))

    # (the gateway's own callbacks, which ``make`` set, are not the probe's)
    client.on_connect, client.on_message = on_connect, on_message
    client.on_subscribe = lambda c, *_: c.publish(echo, b"", qos=0)
    client.on_disconnect, client.on_publish = on_disconnect, None
    client.will_clear()  # the gateway's will is not the probe's to leave
    # (shielded: a probe given up on while it connects, a hedge that lost, must not
    # wait for the connect, and what the connect opens is closed when it ends)
    connecting = asyncio.ensure_future(
        asyncio.to_thread(client.connect, broker.host, broker.port, 10))
    driver = Driver(client)
    try:
        try:
            await asyncio.shield(connecting)
        except (OSError, ValueError) as exc:
            raise BrokerUnreached("unreachable", reason_of(exc)) from exc
        if progress is not None:
            progress.reached.set()
        driver.attach()
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
            driver.close()  # (writes the DISCONNECT, if the socket takes it)
        else:
            connecting.add_done_callback(lambda ended: _closed_late(client, ended))


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


def reason_of(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
