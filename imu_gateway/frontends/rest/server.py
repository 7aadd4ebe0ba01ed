"""The HTTP server: uvicorn in the gateway's loop, with connections that must keep
their deadlines (``_GuardedProtocol``)."""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import socket
import time
from email.utils import formatdate
from http import HTTPStatus
from typing import Any, ClassVar

import uvicorn
from fastapi import FastAPI
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
from uvicorn.server import ServerState

from ...config import HttpConfig, ListenAddress
from ...errors import KINDS, ErrorKind
from ...stats import FrontendCounts
from ...supervise import Frontend, RepeatFilter
from ..common import GatewayLike, json_bytes
from .limits import (
    API,
    BODY_DEADLINE_S,
    HEADER_DEADLINE_S,
    IDLE_S,
    LINGER_BYTES,
    LINGER_S,
    MAX_HEAD,
    MAX_STREAMS,
    SEND_BUFFER,
    STALL_S,
)
from .routes import create_app
from .streams import PEER, StreamHub

log = logging.getLogger("imu_gateway.http")


# ------------------------------------------------------------------ the server


def _cancel(timer: asyncio.TimerHandle | None) -> None:
    if timer is not None:
        timer.cancel()


class _GuardedProtocol(HttpToolsProtocol):
    """uvicorn's HTTP/1.1 protocol with the deadlines uvicorn lacks.  (httptools, named
    rather than uvicorn's "auto", so the behaviour does not depend on what is installed.)

    uvicorn waits for ever for a request's headers and body, so a client that sends
    part of a request, or nothing, holds its connection, and a few hundred such hold
    the connection cap (``limit_concurrency``).  Here:

    - a connection that sends nothing is closed after ``IDLE_S``, as a kept-alive one
      is (uvicorn arms that timer only after an answer);
    - a request's headers must be complete ``HEADER_DEADLINE_S`` after connecting, or
      after the previous answer on a kept-alive connection (a trickle of bytes does
      not extend it);
    - its body ``BODY_DEADLINE_S`` after its headers;
    - its request line and headers are at most ``MAX_HEAD`` bytes.  httptools gathers
      a header by joining its pieces, with no limit of its own: eight clients sending
      a 32 MB header each once held 400 MB.

    A late request is answered 408, a head too large 431, if no answer is under way;
    its connection is then closed.

    For the stream hub, ``write_stalled`` says the client's socket has been full, with
    nothing taken from it, for ``STALL_S``."""

    counters: ClassVar[dict[str, int]] = {}  # the server's (``_protocol_for``)
    write_stalled = False
    _header_timer: asyncio.TimerHandle | None = None
    _body_timer: asyncio.TimerHandle | None = None
    _stall_timer: asyncio.TimerHandle | None = None
    _linger_timer: asyncio.TimerHandle | None = None
    #: Bytes of the current request's line and headers so far; None while its headers
    #: are in (the body is the routes' to limit: ``access.BodyGuard``).
    _head: int | None = 0
    _refused = False  # a 431 was sent: what still comes is dropped
    _dropped = 0  # bytes dropped since

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.timeout_keep_alive_task = self.loop.call_later(
            self.timeout_keep_alive, self.timeout_keep_alive_handler)
        self._await_headers()

    def connection_lost(self, exc: Exception | None) -> None:
        for timer in (self._header_timer, self._body_timer, self._stall_timer,
                      self._linger_timer):
            _cancel(timer)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        """The parser gets at most ``MAX_HEAD`` bytes of a request's head: a head that
        goes on past them is answered 431 before its bytes are kept."""
        if self._refused:
            self._dropped += len(data)
            if self._dropped > LINGER_BYTES:
                # Closing now would reset the connection, the 431 perhaps still unread:
                # the client is left to wait until LINGER_S.
                self.transport.pause_reading()
            return
        while data and not self.transport.is_closing():
            if self._head is None:
                super().data_received(data)
                return
            room = MAX_HEAD - self._head
            if room <= 0:
                self._head_too_large()
                return
            # (the head may end inside the piece, and what follows is counted anew)
            piece, data = data[:room], data[room:]
            self._head += len(piece)
            super().data_received(piece)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self.scope["extensions"] = {PEER: {"connection": self}}  # for stream_peer

    def on_headers_complete(self) -> None:
        _cancel(self._header_timer)
        self._head = None
        _dated(self.server_state)
        super().on_headers_complete()
        # Disarmed by on_message_complete, which comes at once when there is no body.
        self._body_timer = self.loop.call_later(BODY_DEADLINE_S, self._late, "body",
                                                BODY_DEADLINE_S)

    def send_400_response(self, msg: str) -> None:
        _dated(self.server_state)  # (uvicorn's answer to a request it cannot parse)
        super().send_400_response(msg)

    def on_message_complete(self) -> None:
        _cancel(self._body_timer)
        self._head = 0  # a pipelined request's head may follow at once
        super().on_message_complete()

    def on_response_complete(self) -> None:
        pipelined = bool(self.pipeline)  # a request whose headers are in starts now
        super().on_response_complete()
        if not pipelined and not self.transport.is_closing():
            self._await_headers()

    def _await_headers(self) -> None:
        _cancel(self._header_timer)
        self._header_timer = self.loop.call_later(HEADER_DEADLINE_S, self._late, "headers",
                                                  HEADER_DEADLINE_S)

    def _late(self, part: str, seconds: float) -> None:
        if self.transport.is_closing():
            return
        self.counters["request_timeouts"] += 1
        log.debug("http: %s: the request's %s did not come within %g s", self.client,
                  part, seconds)
        self._refuse(ErrorKind.REQUEST_TIMEOUT,
                     f"the request's {part} did not come within {seconds:g} s")
        self._close()

    def _head_too_large(self) -> None:
        for timer in (self._header_timer, self._body_timer):
            _cancel(timer)
        self._refused = True
        log.debug("http: %s: a request's head over %d bytes", self.client, MAX_HEAD)
        if self.cycle is not None and not self.cycle.response_complete:
            # An earlier request on this connection (pipelined) is still being
            # answered, perhaps a stream: the 431 cannot come after it.
            self.transport.abort()
            return
        self._refuse(ErrorKind.HEADERS_TOO_LARGE,
                     f"the request line and headers are over {MAX_HEAD} bytes; "
                     "send fewer or shorter headers")
        # The client is likely still sending.  Closing now would answer its next bytes
        # with a reset, which can reach it before the 431 does: what comes is read and
        # dropped for a while (``LINGER_S``, ``LINGER_BYTES``), or until the client
        # closes (``eof_received``).
        self.transport.write_eof()
        self._linger_timer = self.loop.call_later(LINGER_S, self._close)

    def _refuse(self, kind: ErrorKind, message: str) -> None:
        """Answer a request that never reached the app, if no answer is under way."""
        if self.cycle is not None and self.cycle.response_started \
                and not self.cycle.response_complete:
            return
        row = KINDS[kind]
        body = json_bytes({"error": message, "kind": kind.value})
        _dated(self.server_state)
        head = [b"HTTP/1.1 %d %s\r\n" % (row.status, HTTPStatus(row.status).phrase.encode()),
                *(b"%s: %s\r\n" % h for h in self.server_state.default_headers),
                b"content-type: application/json\r\n",
                b"content-length: %d\r\n" % len(body), b"connection: close\r\n\r\n"]
        self.transport.write(b"".join(head) + body)

    def _close(self) -> None:
        # close() waits until what is buffered is sent: for a client that does not
        # read, for ever.
        if self.transport.get_write_buffer_size():
            self.transport.abort()
        else:
            self.transport.close()

    # The client's socket: asyncio pauses writing when the bytes the kernel would not
    # take pass the high-water mark, and resumes once most are sent.
    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stall_timer is None:
            self._stall_timer = self.loop.call_later(STALL_S, self._stalled)

    def resume_writing(self) -> None:
        super().resume_writing()
        _cancel(self._stall_timer)
        self._stall_timer = None
        self.write_stalled = False

    def _stalled(self) -> None:
        # A timer rather than comparing clocks at the next event: a turn of the loop
        # runs the I/O callbacks before the due timers, so after the loop was merely
        # behind, the socket has been written to (and writing resumed) before this.
        self._stall_timer = None
        self.write_stalled = True

    def abort(self) -> None:
        self.transport.abort()


def _protocol_for(server_counters: dict[str, int]) -> type[_GuardedProtocol]:
    """The protocol class for one server, counting into its counters (uvicorn makes
    each connection's protocol itself, from the class)."""

    class Protocol(_GuardedProtocol):
        counters = server_counters

    return Protocol


class _Server(uvicorn.Server):
    """uvicorn without its signal handlers (the gateway owns SIGINT and SIGTERM), and
    without its tick.  uvicorn's main loop wakes ten times a second, to see whether it
    should exit and to refresh its Date header: on a small box, idle, that is most of
    what the REST server costs.  Here the exit is an event (``should_exit`` sets it),
    and the Date is refreshed when an answer needs it (``_dated``).  The tick's other
    duties are not used here: ``limit_max_requests``, ``callback_notify``.  The
    event is set from the loop's own thread (the gateway's signal handlers are the
    loop's): ``should_exit`` set from another thread would not wake it."""

    def __init__(self, config: uvicorn.Config) -> None:
        assert config.limit_max_requests is None and config.callback_notify is None, \
            "uvicorn's tick did those; this server has no tick"
        self._exit = asyncio.Event()
        super().__init__(config)

    @property
    def should_exit(self) -> bool:
        return self._exit.is_set()

    @should_exit.setter
    def should_exit(self, value: bool) -> None:
        if value:
            self._exit.set()
        else:
            self._exit.clear()

    async def main_loop(self) -> None:
        await self.on_tick(0)  # (uvicorn's first Date header)
        await self._exit.wait()

    @contextlib.contextmanager
    def capture_signals(self) -> Any:
        yield


#: The Date header of the second it was made in, shared by the servers (a reload makes
#: another): (the second, the header).
_DATE: list[tuple[int, tuple[bytes, bytes]]] = [(0, (b"date", b""))]


def _dated(state: ServerState) -> None:
    """The server's Date header made current, at most once a second (what uvicorn's
    tick did): the first of its default headers, as uvicorn puts it."""
    now = int(time.time())
    second, header = _DATE[0]
    if now != second:
        header = (b"date", formatdate(now, usegmt=True).encode())
        _DATE[0] = (now, header)
    headers = state.default_headers
    if headers and headers[0] is not header and headers[0][0] == b"date":
        state.default_headers = [header, *headers[1:]]


class HttpServer(Frontend):
    name = "http"

    def __init__(self, gateway: GatewayLike, config: HttpConfig) -> None:
        super().__init__()
        self.gateway = gateway
        self.config = config
        self.counters = {"requests": 0, "request_timeouts": 0}
        self.hub: StreamHub | None = None
        self._socket: socket.socket | None = None
        self._server: _Server | None = None
        self._task: asyncio.Task[None] | None = None
        self._on_stop: list[Any] = []  # the app's shutdown hooks (uvicorn's lifespan is off)
        self._app: FastAPI | None = None

    async def start(self) -> None:
        """Listen; raises ``OSError`` when the address cannot be bound."""
        self._serve(_bound(self.config.listen))

    def reconfigure(self, config: HttpConfig) -> None:
        """A reload: ``config``'s credentials and rules apply from the next request on
        (the listen address is ``move``'s)."""
        self.config = config.model_copy(update={"listen": self.config.listen})
        if self._app is not None:
            self._app.state.authority.configure(self.config)

    async def move(self, config: HttpConfig) -> bool:
        """Listen at ``config.listen`` instead (a reload, after its answer was sent).
        The new address is bound first: when it cannot be, the server stays where it
        is, and says so.  Then the old server stops as at a shutdown: its streams end
        (their clients reconnect to the new address), its requests finish; the
        sessions go on at the new address."""
        try:
            sock = _bound(config.listen)
        except OSError as exc:
            log.error("http: cannot listen at %s (%s): the REST server stays at %s; fix "
                      "http.listen and apply again", config.listen,
                      exc.strerror or exc, self.config.listen)
            return False
        old = (self._server, self._task, self.hub, self._socket, self._on_stop)
        sessions = self._app.state.authority.sessions if self._app is not None else {}
        self.config = config
        self._serve(sock)
        assert self._app is not None
        self._app.state.authority.sessions = sessions
        await _stop(*old)
        return True

    def _serve(self, sock: socket.socket) -> None:
        self._socket = sock
        self.hub = StreamHub(self.gateway, on_error=self.fail)
        uvicorn_log = logging.getLogger("uvicorn.error")
        if not any(isinstance(f, RepeatFilter) for f in uvicorn_log.filters):
            uvicorn_log.addFilter(RepeatFilter())  # it warns once per odd request
        app = create_app(self.gateway, self.config, self.hub, self.counters)
        self._app = app
        self._on_stop = list(app.router.on_shutdown)  # (the procedures in progress)
        server = self._server = _Server(uvicorn.Config(
            app, log_config=None, log_level="warning", access_log=False, lifespan="off",
            timeout_graceful_shutdown=2, server_header=False,
            http=_protocol_for(self.counters), ws="none", timeout_keep_alive=IDLE_S,
            # every connection and request at once, stalled ones included: 503 beyond
            limit_concurrency=MAX_STREAMS + 100))
        self._task = asyncio.create_task(server.serve(sockets=[sock]), name="http")
        self._task.add_done_callback(lambda task: self._ended(server, task))
        log.info("HTTP on http://%s:%d/ (API %s)", self.config.listen.host, self.port, API)

    def _ended(self, server: _Server, task: asyncio.Task[None]) -> None:
        """uvicorn's server ends only when told to: otherwise it failed."""
        if task.cancelled() or server.should_exit:
            return
        self.fail(task.exception() or RuntimeError("the HTTP server stopped"))

    @property
    def listening(self) -> bool:
        return self._socket is not None

    @property
    def port(self) -> int:
        assert self._socket is not None
        return int(self._socket.getsockname()[1])

    def stats(self) -> FrontendCounts:
        streams = self.hub.open if self.hub is not None else 0
        connections = len(self._server.server_state.connections) if self._server else 0
        return {"clients": connections, "streams": streams,
                "requests": self.counters["requests"],
                "request_timeouts": self.counters["request_timeouts"],
                "dropped_streams": self.hub.dropped if self.hub is not None else 0,
                "skipped_events": self.hub.skipped if self.hub is not None else 0}

    async def stop(self) -> None:
        await _stop(self._server, self._task, self.hub, self._socket, self._on_stop)
        self._socket = None  # a restart listens anew


def _bound(listen: ListenAddress) -> socket.socket:
    """A listening socket at ``listen``; raises ``OSError`` when it cannot be bound."""
    family = socket.AF_INET6 if ":" in listen.host else socket.AF_INET
    # proto given: asyncio sets TCP_NODELAY only on sockets that say they are TCP,
    # and without it each keep-alive answer waits 40 ms for a delayed ACK.
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        # Accepted connections inherit this: the kernel's buffer for a client that
        # stops reading stays small (it may otherwise grow to megabytes), so a
        # stalled stream client is noticed, and dropped, within seconds.
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        sock.bind((listen.host, listen.port))
        sock.listen(512)
    except OSError:
        sock.close()
        raise
    sock.setblocking(False)
    return sock


async def _stop(server: _Server | None, task: asyncio.Task[None] | None,
                hub: StreamHub | None, sock: socket.socket | None, hooks: list[Any]) -> None:
    for hook in hooks:  # uvicorn runs with lifespan off: no shutdown event
        if inspect.isawaitable(done := hook()):
            await done
    if hub is not None:
        hub.close()  # streams end, so their connections can close
    if server is not None and task is not None:
        server.should_exit = True
        await task
    if sock is not None:
        sock.close()
