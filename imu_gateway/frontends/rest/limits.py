"""The REST server's limits and its API prefix, in one place."""

from __future__ import annotations

API = "/api/v1"
STREAM_QUEUE = 64  # events queued per stream client; past it, the oldest are skipped
STALL_S = 5.0  # a stream client whose socket has been full this long (queue full): dropped
KEEPALIVE_S = 15.0  # a comment line on an idle stream, so proxies keep it open
MAX_STREAMS = 1000
SEND_BUFFER = 64 * 1024  # bytes of kernel send buffer per connection
MAX_BODY = 16 * 1024  # a command's arguments are a few bytes; the other routes take none
MAX_HEAD = 16 * 1024  # a request's line and headers (a browser's are under 2 KiB): 431 beyond
LINGER_S = 2.0  # after a 431, what the client still sends is read and dropped this long,
LINGER_BYTES = 1 << 20  # and at most this much, then no more is read (dropping costs CPU)
HEADER_DEADLINE_S = 10.0  # a request's headers, from connecting or from the previous answer
BODY_DEADLINE_S = 10.0  # a request's body, from the end of its headers
IDLE_S = 5  # a connection with no request under way (uvicorn's timeout_keep_alive)
LOGIN_BODY = 4 * 1024  # a login's user name and password
LOGINS_PER_MINUTE = 5  # login attempts per client address; beyond, 429 with Retry-After
LOGIN_WINDOW_S = 60.0
