"""The live stream: Server-Sent Events fed from the cache, and the connection a
stream is judged by (its own socket, never the gateway's loop)."""

from __future__ import annotations

import asyncio
import logging
import typing
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

from fastapi import Request
from fastapi.responses import Response

from ...cache import ALL_EVENTS, EventKind, Snapshot
from ...derived import json_bytes, reading_json
from ..common import GatewayLike
from .limits import KEEPALIVE_S, STALL_S, STREAM_QUEUE

log = logging.getLogger("imu_gateway.http")

KEEP_ALIVE = b": keep-alive\n\n"  # a comment line: what an idle stream sends


# ------------------------------------------------------------------ the live stream


@typing.runtime_checkable
class StreamPeer(typing.Protocol):
    """A stream client's connection, as the hub judges it (``_GuardedProtocol``)."""

    @property
    def write_stalled(self) -> bool:
        """The client's socket has been full, nothing taken from it, for ``STALL_S``."""

    def abort(self) -> None: ...


class Subscription:
    """One stream client's events, queued by the hub until the stream takes them.

    Its cost per event is kept to what an event needs (issue 29, a small box): the
    stream waits on one future, set by the first event that comes; the keep-alive
    is one timer per ``KEEPALIVE_S`` (not one per event, armed and cancelled), that
    wakes the stream only when it has sent nothing for that long."""

    def __init__(self, sensor: str | None, peer: StreamPeer | None) -> None:
        self.sensor = sensor
        self.peer = peer  # None: no socket to judge by (the hub used on its own)
        self.events: deque[bytes] = deque()
        #: the first events (where each sensor stands) are still queued: a queue that
        #: overflows skips the oldest event after them (a slow sensor's state would not
        #: come again before its next reading)
        self.first_queued = False
        self.dropped = False
        self.ended = False  # the client went away, or the hub closed: no more events
        self._loop = asyncio.get_running_loop()
        self._waiter: asyncio.Future[None] | None = None
        self._sent_at = self._loop.time()
        self._keepalive = self._loop.call_at(self._sent_at + KEEPALIVE_S, self._idle)

    def wake(self) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def end(self) -> None:
        self.ended = True
        self._keepalive.cancel()
        self.wake()

    def _idle(self) -> None:
        due = self._sent_at + KEEPALIVE_S
        if self._loop.time() >= due - 0.001:  # (a timer may run a hair early)
            self.wake()  # nothing queued: the stream sends a keep-alive
            due = self._loop.time() + KEEPALIVE_S
        self._keepalive = self._loop.call_at(due, self._idle)

    async def next(self) -> bytes | None:
        """What to send next, once there is something: every event queued, joined
        (they are all due, so joining delays none), or a keep-alive after
        ``KEEPALIVE_S`` without; ``None``: the stream ends."""
        if not self.events and not self.ended:
            self._waiter = self._loop.create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        if self.ended or self.dropped:
            return None
        self._sent_at = self._loop.time()
        if not self.events:
            return KEEP_ALIVE
        chunk = self.events[0] if len(self.events) == 1 else b"".join(self.events)
        self.events.clear()
        self.first_queued = False
        return chunk


class StreamHub:
    """Server-Sent Events: every reading (and status change) to every subscriber of
    its sensor.  An event is formatted once, whatever the number of subscribers.

    At most ``STREAM_QUEUE`` events wait per subscriber.  When one more comes, the
    subscriber is judged by its own socket, never by how far behind its queue is (the
    queue also fills while the gateway's loop is behind, its client reading well):

    - its client has taken nothing for ``STALL_S`` (the socket stayed full): dropped,
      its connection closed, rather than the gateway buffering without bound;
    - otherwise its oldest event is skipped (and counted): the client stays, and
      catches up with the newest readings."""

    def __init__(self, gateway: GatewayLike,
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        self.gateway = gateway
        self.subscribers: set[Subscription] = set()  # those events go to
        # Streams not yet ended, dropped ones included (until their connection has
        # closed): they count against MAX_STREAMS.
        self.open = 0
        self.dropped = 0  # subscribers dropped as stalled
        self.skipped = 0  # events skipped for subscribers whose queue was full
        self.closed = False
        self.history = gateway.history  # the gateway's, shared with the other front ends
        # Prompt only while a stream is open (``_claim``): a REST server nobody
        # streams from lets the buses hand their turns over lazily.
        self._unsubscribe = gateway.cache.subscribe(self._on_cache_event, on_error,
                                                    ALL_EVENTS, prompt=False)
        self._release: Callable[[], None] | None = None

    def _claim(self) -> None:
        if self._release is None:
            self._release = self.gateway.cache.claim_prompt()

    def _release_if_idle(self) -> None:
        if (self.closed or not self.subscribers) and self._release is not None:
            self._release()
            self._release = None

    def _on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if not self.subscribers or kind is EventKind.SETTINGS:  # (not in the stream)
            return
        if snap.alarm is not None:  # (an ALARM event)
            event = b"event: alarm\ndata: %s\n\n" % json_bytes(snap.alarm.to_json())
        else:
            event = _event("reading" if kind is EventKind.READING else "status", snap)
        for sub in list(self.subscribers):
            if sub.sensor is not None and sub.sensor != snap.name:
                continue
            if len(sub.events) >= STREAM_QUEUE:
                if sub.peer is not None and sub.peer.write_stalled:
                    self._drop(sub)
                    continue
                if sub.first_queued and len(sub.events) > 1:
                    del sub.events[1]
                else:
                    sub.events.popleft()
                self.skipped += 1
            sub.events.append(event)
            sub.wake()

    def _drop(self, sub: Subscription) -> None:
        sub.dropped = True
        sub.events.clear()
        self.subscribers.discard(sub)
        self._release_if_idle()
        self.dropped += 1
        log.info("http: dropped a stream client that took nothing for %g s", STALL_S)
        # Its send waits on a full socket, so the stream could only end once the client
        # read again (a zero window is kept open for ever): the connection goes now.
        assert sub.peer is not None
        sub.peer.abort()
        sub.end()

    def subscribe(self, sensor: str | None, peer: StreamPeer | None = None) -> Subscription:
        """A new stream's subscription (``unsubscribe`` it when the stream ends), its
        first events queued: where each sensor (or ``sensor``) stands now.  They are
        taken before it listens, so a write they show is not queued again after them,
        and none comes between the two."""
        first = None if self.closed else self._first_events(sensor)
        sub = Subscription(sensor, peer)
        self.open += 1
        if first is None:
            sub.end()
        else:
            sub.events.append(first)
            sub.first_queued = True
            self.subscribers.add(sub)
        return sub

    def _first_events(self, sensor: str | None) -> bytes:
        """Where each sensor (or ``sensor``) stands now, prompt first: what the claim
        applies, the snapshots show."""
        self._claim()
        names = [sensor] if sensor is not None else self.gateway.cache.names
        try:  # (a sensor a reload removed since the route looked)
            snaps = self.gateway.cache.snapshots(names)
        except Exception:
            self._release_if_idle()
            raise
        return b"".join(_event("reading" if snap.has_reading else "status", snap)
                        for snap in snaps)

    def unsubscribe(self, sub: Subscription) -> None:
        sub.end()
        self.subscribers.discard(sub)
        self._release_if_idle()
        self.open -= 1

    def close(self) -> None:
        self.closed = True
        for sub in list(self.subscribers):
            sub.end()
        self._unsubscribe()
        self._release_if_idle()


def _event(name: str, snap: Snapshot) -> bytes:
    """One event.  No ``id:``: a stream is not resumable (a reconnecting client gets
    each sensor's current state first, and the past from ``…/history``), and the
    combined stream's readings have no common order an id could name; the reading's
    own ``seq`` is in its data."""
    return b"event: %s\ndata: %s\n\n" % (name.encode(), reading_json(snap))


class EventStream(Response):
    """The stream's answer: an ASGI response that sends each chunk of its subscription
    in the loop turn it comes.  Starlette's ``StreamingResponse`` runs the stream in
    a task group beside a task that waits for the client to go; here that wait is a
    plain task that ends the subscription, and the stream is the request's own
    task, with nothing between the hub and ``send`` (measured: docs/benchmarks.md,
    "CPU per sample in the front ends")."""

    media_type = "text/event-stream"

    def __init__(self, hub: StreamHub, sensor: str | None, peer: StreamPeer | None,
                 headers: Mapping[str, str] | None = None) -> None:
        self.hub, self.sensor, self.peer = hub, sensor, peer
        self.status_code = 200
        self.background = None
        self.init_headers(headers)

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        sub = self.hub.subscribe(self.sensor, self.peer)
        gone = asyncio.ensure_future(_until_disconnect(receive, sub))
        try:
            await send({"type": "http.response.start", "status": self.status_code,
                        "headers": self.raw_headers})
            chunk = await sub.next()  # (the first: ``StreamHub.subscribe``)
            while chunk is not None:
                await send({"type": "http.response.body", "body": chunk, "more_body": True})
                chunk = await sub.next()
            await send({"type": "http.response.body", "body": b"", "more_body": False})
        finally:
            gone.cancel()
            self.hub.unsubscribe(sub)


async def _until_disconnect(receive: Any, sub: Subscription) -> None:
    """End ``sub`` when its client goes away (ASGI's ``http.disconnect``)."""
    while (await receive())["type"] != "http.disconnect":
        pass
    sub.end()


PEER = "imu_gateway.peer"  # the ASGI scope extension that carries a request's connection


def stream_peer(request: Request) -> StreamPeer | None:
    """The connection a request came on, when the server's ``_GuardedProtocol``
    serves it."""
    peer = request.scope.get("extensions", {}).get(PEER, {}).get("connection")
    return peer if isinstance(peer, StreamPeer) else None
