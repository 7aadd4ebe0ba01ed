"""The REST API, the live stream, the metrics and the dashboard (docs/rest.md).

FastAPI on uvicorn, inside the gateway's own event loop: the gateway owns the signals
and the shutdown (uvicorn would install handlers of its own; ``_Server`` stops it).
Every read is answered from the cache; ``max_age_ms`` is the one way a client can
cause bus traffic, and identical on-demand reads share one transaction.

Errors are one JSON shape, ``{"error": "...", "kind": "..."}``, with the status codes
docs/rest.md lists: 401/403 auth, 404 unknown sensor or command, 408 a request that
did not come in time, 409 busy, 413 a body too large, 422 bad arguments or a command
the series lacks, 431 headers too large, 503 no reading yet, 504 the sensor did not
answer; 502 when the sensor answered that the command failed.

A client cannot hold the server: a connection is closed when a request's headers or
body are late, when its headers are over ``MAX_HEAD`` bytes (431), or when it stays
idle (``_GuardedProtocol``); a body is limited by its route (``access.BodyGuard``);
and a stream client is dropped when its own socket stays full, never because the
gateway is behind (``StreamHub``).

The command routes are made from the command catalogue, so the OpenAPI document shows
each command's own arguments.
"""

from __future__ import annotations

from .limits import (
    API,
    BODY_DEADLINE_S,
    HEADER_DEADLINE_S,
    IDLE_S,
    KEEPALIVE_S,
    MAX_BODY,
    MAX_HEAD,
    MAX_STREAMS,
    STALL_S,
    STREAM_QUEUE,
)
from .routes import create_app, openapi_document
from .server import HttpServer
from .streams import StreamHub

__all__ = ["API", "BODY_DEADLINE_S", "HEADER_DEADLINE_S", "IDLE_S", "KEEPALIVE_S", "MAX_BODY",
           "MAX_HEAD", "MAX_STREAMS", "STALL_S", "STREAM_QUEUE", "HttpServer", "StreamHub",
           "create_app", "openapi_document"]
