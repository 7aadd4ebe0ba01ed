"""A live stream of the REST server's hub, without the HTTP server."""

from __future__ import annotations

from collections.abc import AsyncGenerator

from imu_gateway.frontends.rest.streams import StreamHub, StreamPeer


async def hub_stream(hub: StreamHub, sensor: str | None,
                     peer: StreamPeer | None = None) -> AsyncGenerator[bytes, None]:
    """A live stream of ``hub`` as an iterator of chunks, without the HTTP server: what
    the server's ``EventStream`` sends (each chunk ``next`` gives, the first events
    queued by the subscription first)."""
    sub = hub.subscribe(sensor, peer)
    try:
        while (chunk := await sub.next()) is not None:
            yield chunk
    finally:
        hub.unsubscribe(sub)
