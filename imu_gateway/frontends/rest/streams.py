"""The live stream: Server-Sent Events fed from the cache, and the connection a
stream is judged by (its own socket, never the gateway's loop)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import typing
from collections import deque
from collections.abc import AsyncGenerator, Callable

from fastapi import Request

from ...cache import ALL_EVENTS, EventKind, Snapshot
from ...derived import json_bytes, reading_json
from ..common import GatewayLike
from .limits import KEEPALIVE_S, STALL_S, STREAM_QUEUE

log = logging.getLogger("imu_gateway.http")


# ------------------------------------------------------------------ the live stream


@typing.runtime_checkable
class StreamPeer(typing.Protocol):
    """A stream client's connection, as the hub judges it (``_GuardedProtocol``)."""

    @property
    def write_stalled(self) -> bool:
        """The client's socket has been full, nothing taken from it, for ``STALL_S``."""

    def abort(self) -> None: ...


class _Subscriber:
    def __init__(self, sensor: str | None, peer: StreamPeer | None) -> None:
        self.sensor = sensor
        self.peer = peer  # None: no socket to judge by (the hub used on its own)
        self.events: deque[bytes] = deque()
        self.wake = asyncio.Event()
        self.dropped = False


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
        self.subscribers: set[_Subscriber] = set()  # those events go to
        # Streams not yet ended, dropped ones included (until their connection has
        # closed): they count against MAX_STREAMS.
        self.open = 0
        self.dropped = 0  # subscribers dropped as stalled
        self.skipped = 0  # events skipped for subscribers whose queue was full
        self.closing = asyncio.Event()
        self.history = gateway.history  # the gateway's, shared with the other front ends
        self._unsubscribe = gateway.cache.subscribe(self._on_cache_event, on_error,
                                                    ALL_EVENTS)

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
                sub.events.popleft()
                self.skipped += 1
            sub.events.append(event)
            sub.wake.set()

    def _drop(self, sub: _Subscriber) -> None:
        sub.dropped = True
        sub.events.clear()
        self.subscribers.discard(sub)
        self.dropped += 1
        log.info("http: dropped a stream client that took nothing for %g s", STALL_S)
        # Its send waits on a full socket, so the stream could only end once the client
        # read again (a zero window is kept open for ever): the connection goes now.
        assert sub.peer is not None
        sub.peer.abort()
        sub.wake.set()

    async def stream(self, sensor: str | None,
                     peer: StreamPeer | None = None) -> AsyncGenerator[bytes, None]:
        sub = _Subscriber(sensor, peer)
        self.subscribers.add(sub)
        self.open += 1
        try:
            names = [sensor] if sensor is not None else self.gateway.cache.names
            for name in names:  # where each sensor stands now, first
                snap = self.gateway.cache.snapshot(name)
                yield _event("reading" if snap.has_reading else "status", snap)
            while not self.closing.is_set() and not sub.dropped:
                if not sub.events:
                    sub.wake.clear()
                    # (asyncio.timeout, not wait_for: wait_for wraps the wait in a task
                    # of its own, for every event)
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(KEEPALIVE_S):
                            await sub.wake.wait()
                    if not sub.events:
                        yield b": keep-alive\n\n"
                        continue
                yield sub.events.popleft()
        finally:
            self.subscribers.discard(sub)
            self.open -= 1

    def close(self) -> None:
        self.closing.set()
        for sub in self.subscribers:
            sub.wake.set()
        self._unsubscribe()


def _event(name: str, snap: Snapshot) -> bytes:
    """One event.  No ``id:``: a stream is not resumable (a reconnecting client gets
    each sensor's current state first, and the past from ``…/history``), and the
    combined stream's readings have no common order an id could name; the reading's
    own ``seq`` is in its data."""
    return b"event: %s\ndata: %s\n\n" % (name.encode(), reading_json(snap))


PEER = "imu_gateway.peer"  # the ASGI scope extension that carries a request's connection


def stream_peer(request: Request) -> StreamPeer | None:
    """The connection a request came on, when the server's ``_GuardedProtocol``
    serves it."""
    peer = request.scope.get("extensions", {}).get(PEER, {}).get("connection")
    return peer if isinstance(peer, StreamPeer) else None
