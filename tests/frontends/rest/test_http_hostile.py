"""The HTTP front end against careless and hostile clients (docs/rest.md, "Slow and
idle clients").

The connection rules (idle connections, late headers, late bodies) are tested against
the real gateway process (``python -m imu_gateway run``) on a simulated line; the stream
rules in-process (``harness.running``), where the test can hold up the gateway's own
event loop.  The time limits come from ``imu_gateway.frontends.rest``.  Waits for
something to happen are generous deadlines on a condition; the one measurement is
the time to an answer with 400 idle connections open.
"""

from __future__ import annotations

import asyncio
import contextlib
import email.utils
import itertools
import json
import selectors
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import pytest
import yaml
from support.harness import free_port, interrupt, running, until
from support.streams import hub_stream

from imu_gateway.app import Gateway
from imu_gateway.config import config_from_dict
from imu_gateway.frontends.rest import (
    BODY_DEADLINE_S,
    HEADER_DEADLINE_S,
    IDLE_S,
    MAX_HEAD,
    STREAM_QUEUE,
    HttpServer,
    StreamHub,
)
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimulatorThread, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
LINE_FAST = 460800  # the stream tests' line: the fastest the config takes
TOKEN = "t0ken-for-tests"
API = "/api/v1"
# Each limit is timed from a moment before the gateway's own start of it (before the
# connect, before the request), so it can only seem longer here; EARLY is for rounding.
EARLY = 0.5  # s: how much sooner than its limit the gateway may seem to act
LATE = 30.0  # s: how much later it may act, on a loaded machine

Address = tuple[str, int]


# ------------------------------------------------------------------ the gateway process


def _get(url: str) -> int:
    with urllib.request.urlopen(url, timeout=10) as response:
        response.read()
        return int(response.status)


@dataclass(frozen=True)
class Process:
    address: Address
    pid: int


@pytest.fixture(scope="module")
def gateway_process(gateway_pid: Process) -> Address:
    return gateway_pid.address


@pytest.fixture(scope="module")
def gateway_pid(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Process]:
    """``python -m imu_gateway run`` with HTTP (commands on) and one polled AH; its address
    and process id once ``/api/v1/health`` answers."""
    tmp = tmp_path_factory.mktemp("hostile")
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST, source=Motion.from_seed(3))
    with simulated([sim]) as line:
        port = free_port()
        cfg = {"gateway_id": "hostile",
               "buses": [{"name": "a", "port": line.path, "baudrate": FAST,
                          "protocol": "native",
                          "sensors": [{"name": "boom", "series": "AH", "poll_hz": 10}]}],
               "http": {"listen": f"127.0.0.1:{port}", "token": TOKEN,
                        "allow_commands": True}}
        path = tmp / "gateway.yaml"
        path.write_text(yaml.safe_dump(cfg))
        log_path = tmp / "gateway.log"
        with log_path.open("wb") as log:
            process = subprocess.Popen(
                [sys.executable, "-m", "imu_gateway", "run", "-c", str(path)],
                stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 30
            while True:
                if process.poll() is not None:
                    raise AssertionError(f"the gateway exited:\n{log_path.read_text()}")
                with contextlib.suppress(OSError, urllib.error.URLError):
                    if _get(f"http://127.0.0.1:{port}{API}/health") == 200:
                        break
                assert time.monotonic() < deadline, "the gateway's API did not answer"
                time.sleep(0.05)
            yield Process(("127.0.0.1", port), process.pid)
            assert process.poll() is None, "the gateway exited"
        finally:
            interrupt(process)
    assert "Traceback" not in log_path.read_text()


def _connect(address: Address) -> socket.socket:
    return socket.create_connection(address, timeout=10)


def _answer(sock: socket.socket) -> bytes:
    """One whole answer with a ``content-length`` (the head and its body)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        assert chunk, f"closed before a whole answer: {data!r}"
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n")
                  if line.lower().startswith(b"content-length:"))
    while len(body) < length:
        chunk = sock.recv(65536)
        assert chunk, "closed in the body"
        body += chunk
    return head + b"\r\n\r\n" + body


def _until_closed(started: dict[socket.socket, float], timeout: float,
                  trickle: socket.socket | None = None) -> dict[socket.socket, tuple[float, bytes]]:
    """Wait until the gateway has closed each socket: for each, the seconds from its
    time in ``started`` to the end of its stream, and what it received.  One byte a
    second goes to ``trickle`` meanwhile (a header that never ends)."""
    closed: dict[socket.socket, tuple[float, bytes]] = {}
    received = dict.fromkeys(started, b"")
    deadline = time.monotonic() + timeout
    next_drip = time.monotonic() + 1.0
    with selectors.DefaultSelector() as selector:
        for sock in started:
            selector.register(sock, selectors.EVENT_READ)
        while len(closed) < len(started):
            assert time.monotonic() < deadline, \
                f"{len(started) - len(closed)} connections still open after {timeout} s"
            for key, _ in selector.select(0.2):
                ready = key.fileobj
                assert isinstance(ready, socket.socket)
                try:
                    chunk = ready.recv(65536)
                except ConnectionResetError:
                    chunk = b""
                if chunk:
                    received[ready] += chunk
                    continue
                closed[ready] = (time.monotonic() - started[ready], received[ready])
                selector.unregister(ready)
            if trickle is not None and trickle not in closed and time.monotonic() > next_drip:
                next_drip += 1.0
                with contextlib.suppress(OSError):  # it may be closing right now
                    trickle.sendall(b"a")
    return closed


@contextlib.contextmanager
def _sockets() -> Iterator[list[socket.socket]]:
    """A list of sockets, every one closed at the end."""
    socks: list[socket.socket] = []
    try:
        yield socks
    finally:
        for sock in socks:
            sock.close()


def test_400_idle_connections_leave_health_answered_within_2_s(
        gateway_process: Address) -> None:
    with _sockets() as idle:
        opened: dict[socket.socket, float] = {}
        for _ in range(400):
            before = time.monotonic()
            sock = _connect(gateway_process)
            opened[sock] = before
            idle.append(sock)

        start = time.monotonic()
        with _connect(gateway_process) as fresh:
            fresh.sendall(f"GET {API}/health HTTP/1.1\r\nHost: t\r\n\r\n".encode())
            answer = _answer(fresh)
        took = time.monotonic() - start
        assert answer.startswith(b"HTTP/1.1 200 "), answer[:200]
        assert took < 2.0, f"/health took {took:.2f} s with 400 idle connections"

        # Held meanwhile, then closed by the gateway: a connection that never sends a
        # byte is closed as an idle kept-alive one is (it used to be held for ever).
        closed = _until_closed(opened, IDLE_S + LATE)
        soonest = min(seconds for seconds, _ in closed.values())
        assert soonest >= IDLE_S - EARLY, f"an idle connection closed after {soonest:.2f} s"
        assert all(data == b"" for _, data in closed.values())  # closed, nothing said
        print(f"/health in {took * 1000:.1f} ms with 400 idle connections")


def _date(answer: bytes) -> float:
    """The Date header of a raw answer, as a POSIX time."""
    head = answer.split(b"\r\n\r\n", 1)[0].decode("latin-1")
    dates = [line.split(":", 1)[1].strip() for line in head.split("\r\n")[1:]
             if line.lower().startswith("date:")]
    assert len(dates) == 1, head
    return email.utils.parsedate_to_datetime(dates[0]).timestamp()


def test_the_date_header_is_the_second_of_the_answer(gateway_process: Address) -> None:
    """uvicorn refreshes its Date in a tick the gateway does without (it woke an idle
    gateway ten times a second): each answer's Date is still its own second, uvicorn's
    own 400 to a request it cannot parse too."""
    dates = []
    for request, status in ((f"GET {API}/health HTTP/1.1\r\nHost: x\r\n\r\n", b"200"),
                            (f"GET {API}/health HTTP/1.1\r\nHost: x\r\n\r\n", b"200"),
                            ("GARBAGE\r\n\r\n", b"400")):
        time.sleep(max(0.0, int(time.time()) + 1.05 - time.time()))  # (a new second)
        with _connect(gateway_process) as sock:
            before = time.time()
            sock.sendall(request.encode())
            answer = _answer(sock)
            after = time.time()
        assert answer.startswith(b"HTTP/1.1 " + status + b" "), answer
        dates.append(_date(answer))
        assert int(before) <= dates[-1] <= after, (request, before, dates[-1], after)
    assert dates == sorted(set(dates))


def test_partial_headers_are_closed_after_the_header_deadline(
        gateway_process: Address) -> None:
    started = time.time()
    with _sockets() as socks:
        partial_at = time.monotonic()
        partial = _connect(gateway_process)
        socks.append(partial)
        partial.sendall(f"GET {API}/health HTTP/1.1\r\nHost: x\r\n".encode())

        # A trickle of bytes does not extend the deadline.
        trickle_at = time.monotonic()
        trickle = _connect(gateway_process)
        socks.append(trickle)
        trickle.sendall(f"GET {API}/health HTTP/1.1\r\nHost: x\r\nX-Slow: ".encode())

        # On a kept-alive connection the next request's headers are due that long
        # after the previous answer (timed here from before its request).
        kept = _connect(gateway_process)
        socks.append(kept)
        kept_at = time.monotonic()
        kept.sendall(f"GET {API}/health HTTP/1.1\r\nHost: x\r\n\r\n".encode())
        assert _answer(kept).startswith(b"HTTP/1.1 200 ")
        kept.sendall(f"GET {API}/health HTTP/1.1\r\n".encode())

        closed = _until_closed({partial: partial_at, trickle: trickle_at, kept: kept_at},
                               HEADER_DEADLINE_S + LATE, trickle=trickle)
        for sock, what in ((partial, "partial headers"), (trickle, "a trickle"),
                           (kept, "a kept-alive connection's partial headers")):
            seconds, data = closed[sock]
            assert seconds >= HEADER_DEADLINE_S - EARLY, (what, seconds)
            assert data.startswith(b"HTTP/1.1 408 "), (what, data)
            assert b'"kind":"request_timeout"' in data, (what, data)
            # (the Date of its own second, not of the last request's)
            assert _date(data) >= int(started + HEADER_DEADLINE_S - EARLY), (what, data)
    assert _get(f"http://{gateway_process[0]}:{gateway_process[1]}{API}/health") == 200


def test_a_partial_body_is_closed_after_the_body_deadline(gateway_process: Address) -> None:
    body = b'{"type": "relative"}'
    with _connect(gateway_process) as sock:
        sent = time.monotonic()
        sock.sendall(f"POST {API}/sensors/boom/commands/set_zero_type HTTP/1.1\r\n"
                     f"Host: x\r\nAuthorization: Bearer {TOKEN}\r\n"
                     f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
                     "\r\n".encode() + body[:5])
        seconds, data = _until_closed({sock: sent}, BODY_DEADLINE_S + LATE)[sock]
    assert seconds >= BODY_DEADLINE_S - EARLY, seconds
    assert data.startswith(b"HTTP/1.1 408 "), data
    assert b"body" in data and b'"kind":"request_timeout"' in data, data
    host, port = gateway_process
    with urllib.request.urlopen(f"http://{host}:{port}/metrics", timeout=10) as response:
        metrics = response.read().decode()
    counted = next(float(line.split()[1]) for line in metrics.splitlines()
                   if line.startswith("imu_gateway_http_request_timeouts_total "))
    assert counted >= 1


# ------------------------------------------------------------------ sizes


def _head(extra: int = 0, path: str = f"{API}/health") -> bytes:
    """A request's line and headers of exactly ``MAX_HEAD + extra`` bytes."""
    start = f"GET {path} HTTP/1.1\r\nHost: x\r\nX-Pad: ".encode()
    return start + b"a" * (MAX_HEAD + extra - len(start) - 4) + b"\r\n\r\n"


def _send_all_and_answer(address: Address, data: bytes) -> bytes:
    """Send ``data`` (the gateway may stop taking it), then read until it closes."""
    with _connect(address) as sock:
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            sock.sendall(data)
        answer = b""
        with contextlib.suppress(ConnectionResetError):
            while chunk := sock.recv(65536):
                answer += chunk
        return answer


def test_a_head_over_16_KiB_is_answered_431_and_one_of_16_KiB_is_served(
        gateway_process: Address) -> None:
    with _connect(gateway_process) as sock:
        sock.sendall(_head(0))
        assert _answer(sock).startswith(b"HTTP/1.1 200 ")
    for what, data in (
            ("one byte over", _head(1)),
            ("a 1 MB header", _head(1 << 20)),
            ("a 20 KiB request line", f"GET /{'a' * 20_000} HTTP/1.1\r\n\r\n".encode()),
            ("ten thousand short headers",
             f"GET {API}/health HTTP/1.1\r\n".encode() + b"X-A: b\r\n" * 10_000 + b"\r\n")):
        answer = _send_all_and_answer(gateway_process, data)
        assert answer.startswith(b"HTTP/1.1 431 "), (what, answer[:300])
        body = json.loads(answer.partition(b"\r\n\r\n")[2])
        assert body["kind"] == "headers_too_large", (what, body)
        assert f"over {MAX_HEAD} bytes" in body["error"], (what, body)
    # Behind a request still being answered (a stream) on the same connection: the
    # connection is closed, the 431 not written into the stream (nor after it).
    answer = _send_all_and_answer(
        gateway_process,
        f"GET {API}/stream HTTP/1.1\r\nHost: x\r\n\r\n".encode() + _head(100_000))
    assert b" 431 " not in answer, answer[:300]
    assert _get(f"http://{gateway_process[0]}:{gateway_process[1]}{API}/health") == 200


def _rss_kib(pid: int) -> int:
    with open(f"/proc/{pid}/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))


def _flood(address: Address, head: bytes, count: int, size: int) -> list[bytes]:
    """``count`` connections, each sending ``head`` and then ``size`` more bytes of
    ``a`` as fast as the gateway takes them, until they are sent or it closes; what
    each received."""
    socks = [_connect(address) for _ in range(count)]
    sent = dict.fromkeys(socks, 0)
    received = dict.fromkeys(socks, b"")
    deadline = time.monotonic() + HEADER_DEADLINE_S + LATE
    with selectors.DefaultSelector() as selector:
        for sock in socks:
            sock.setblocking(False)
            sock.sendall(head)
            selector.register(sock, selectors.EVENT_READ | selectors.EVENT_WRITE)
        filler = b"a" * 65536
        while selector.get_map():
            assert time.monotonic() < deadline, "connections still open"
            for key, events in selector.select(0.2):
                ready = key.fileobj
                assert isinstance(ready, socket.socket)
                try:
                    if events & selectors.EVENT_READ:
                        chunk = ready.recv(65536)
                        received[ready] += chunk
                        if not chunk:
                            raise ConnectionResetError
                    if events & selectors.EVENT_WRITE and sent[ready] < size:
                        sent[ready] += ready.send(filler)
                        if sent[ready] >= size:
                            selector.modify(ready, selectors.EVENT_READ)
                except (BrokenPipeError, ConnectionResetError):
                    selector.unregister(ready)
                    ready.close()
                except BlockingIOError:
                    pass
    return list(received.values())


def test_fifty_endless_heads_and_bodies_before_authentication_hold_under_20_MB(
        gateway_pid: Process) -> None:
    """What a connection may make the gateway hold before it is authenticated is
    bounded: 50 clients each sending a header line of 8 MB, then 50 unauthorised
    commands each with a body of 8 MB.  (Each head alone once held its 8 MB.)"""
    before = _rss_kib(gateway_pid.pid)
    peak = before
    stop = False

    def sample() -> None:
        nonlocal peak
        while not stop:
            peak = max(peak, _rss_kib(gateway_pid.pid))
            time.sleep(0.01)

    sampler = threading.Thread(target=sample)
    sampler.start()
    try:
        heads = _flood(gateway_pid.address,
                       f"GET {API}/health HTTP/1.1\r\nHost: x\r\nX-Long: ".encode(),
                       50, 8 << 20)
        bodies = _flood(gateway_pid.address,
                        f"POST {API}/sensors/boom/commands/set_zero_type HTTP/1.1\r\n"
                        f"Host: x\r\nContent-Type: application/json\r\n"
                        f"Content-Length: {8 << 20}\r\n\r\n".encode(), 50, 8 << 20)
    finally:
        stop = True
        sampler.join()
    grown = (peak - before) / 1024
    print(f"RSS {before / 1024:.0f} MB, at most {grown:.1f} MB more")
    assert grown < 20, f"the gateway's RSS grew by {grown:.1f} MB"
    assert all(answer.startswith(b"HTTP/1.1 431 ") for answer in heads), \
        {answer[:40] for answer in heads}
    assert all(answer.startswith(b"HTTP/1.1 401 ") for answer in bodies), \
        {answer[:40] for answer in bodies}
    assert _get(f"http://{gateway_pid.address[0]}:{gateway_pid.address[1]}{API}/health") == 200


# ------------------------------------------------------------------ streams, in-process


@contextlib.contextmanager
def _fast_stream() -> Iterator[tuple[SimulatorThread, dict[str, Any]]]:
    """A native AH polled as fast as a 460800 baud line goes (over 200 readings a
    second), and a config serving it.  Polled rather than streaming: a gateway
    stopping a 200 Hz stream now and then takes 10-20 s to stop its bus."""
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=LINE_FAST,
                      source=Motion.from_seed(5))
    with simulated([sim]) as line:
        yield line, {"gateway_id": "hostile",
                     "buses": [{"name": "a", "port": line.path, "baudrate": LINE_FAST,
                                "protocol": "native",
                                "sensors": [{"name": "boom", "series": "AH",
                                             "poll_hz": 0}]}],
                     "http": {"listen": "127.0.0.1:0"}}


def _http_of(gateway: Gateway) -> tuple[HttpServer, StreamHub]:
    server = gateway.http
    assert server is not None and server.hub is not None
    return server, server.hub


async def _reading_seqs(response: httpx.Response) -> AsyncIterator[int]:
    """The sequence number of each ``reading`` event of a stream (its data's ``seq``)."""
    name = ""
    async for line in response.aiter_lines():
        if line.startswith("event: "):
            name = line.removeprefix("event: ")
        elif line.startswith("data: ") and name == "reading":
            yield int(json.loads(line.removeprefix("data: "))["seq"])
        elif not line:
            name = ""


def _hold_the_loop(done: Callable[[], bool], at_most: float) -> None:
    """Block the calling event loop (time.sleep) until ``done()``, as a long callback
    in the gateway would."""
    deadline = time.monotonic() + at_most
    while not done() and time.monotonic() < deadline:
        time.sleep(0.01)


@pytest.mark.anyio
async def test_a_reading_stream_client_is_kept_while_the_gateways_loop_is_behind() -> None:
    with _fast_stream() as (line, cfg):

        async with running(cfg) as gateway:
            server, hub = _http_of(gateway)
            await until(lambda: gateway.cache.snapshot("boom").seq >= 10, timeout=30)
            async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{server.port}",
                                         timeout=30) as http, \
                    http.stream("GET", f"{API}/sensors/boom/stream") as response:
                assert response.status_code == 200
                seqs = _reading_seqs(response)
                seen = [await anext(seqs), await anext(seqs)]  # flowing

                # The loop held up while far more than STREAM_QUEUE readings
                # arrive (at over 200 a second, under a second).
                frames = line.bus.stats.answer_frames
                asyncio.get_running_loop().call_soon(
                    _hold_the_loop,
                    lambda: line.bus.stats.answer_frames >= frames + 3 * STREAM_QUEUE,
                    20.0)
                # Its queue overflowed: the client, reading, must not be dropped.
                await until(lambda: hub.skipped + hub.dropped > 0, timeout=30)
                assert hub.dropped == 0
                newest = gateway.cache.snapshot("boom").seq
                async with asyncio.timeout(30):
                    async for seq in seqs:
                        seen.append(seq)
                        if seq >= newest + 20:
                            break
                assert hub.dropped == 0 and len(hub.subscribers) == 1
                assert not response.is_closed
            assert seen == sorted(set(seen))  # in order, none twice
            gaps = [b - a for a, b in itertools.pairwise(seen) if b - a > 1]
            assert gaps, "the readings behind were skipped, not all sent"
            stats = server.stats()
            assert stats["dropped_streams"] == 0 and stats["skipped_events"] == hub.skipped



@pytest.mark.anyio
async def test_a_stream_client_that_never_reads_is_dropped_and_disconnected() -> None:
    with _fast_stream() as (_, cfg):

        async with running(cfg) as gateway:
            server, hub = _http_of(gateway)
            await until(lambda: gateway.cache.snapshot("boom").seq >= 10, timeout=30)
            with socket.socket() as sock:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
                sock.setblocking(False)
                loop = asyncio.get_running_loop()
                await loop.sock_connect(sock, ("127.0.0.1", server.port))
                await loop.sock_sendall(sock, f"GET {API}/sensors/boom/stream HTTP/1.1"
                                              "\r\nHost: t\r\n\r\n".encode())
                await until(lambda: len(hub.subscribers) == 1, timeout=30)
                await until(lambda: hub.dropped >= 1, timeout=60)
                # The gateway ended the stream and closed the connection itself,
                # the client still not reading.
                await until(lambda: hub.open == 0, timeout=30)
                await until(lambda: server.stats()["clients"] == 0, timeout=30)
                assert server.stats()["dropped_streams"] == 1
                async with httpx.AsyncClient(
                        base_url=f"http://127.0.0.1:{server.port}", timeout=30) as http:
                    assert (await http.get(f"{API}/health")).status_code == 200



# ------------------------------------------------------------------ the hub's rule


class _Peer:
    """A stream client's connection as the hub sees it."""

    def __init__(self, stalled: bool) -> None:
        self.write_stalled = stalled
        self.aborted = False

    def abort(self) -> None:
        self.aborted = True


@pytest.mark.anyio
async def test_the_hub_skips_the_oldest_for_a_client_behind_and_drops_only_a_stalled_one() -> None:
    config = config_from_dict({"buses": [{"name": "a", "port": "/dev/null",
                                          "protocol": "native",
                                          "sensors": [{"name": "s", "series": "AH"}]}]},
                              env={})
    gateway = Gateway(config)
    events: list[object] = []
    gateway.cache.subscribe(lambda kind, snap: events.append(kind))
    hub = StreamHub(gateway)
    reading, stalled = _Peer(stalled=False), _Peer(stalled=True)
    behind, stuck = hub_stream(hub, "s", reading), hub_stream(hub, "s", stalled)
    bare = hub_stream(hub, "s")
    for stream in (behind, stuck, bare):
        assert b"event: status" in await anext(stream)  # subscribed; reads no further
    sample = Motion.from_seed(3).sample(1.0)
    for _ in range(STREAM_QUEUE + 10):
        gateway.cache.publish("s", sample)

    # The stalled client is dropped once its queue is full, its connection closed;
    # the others (a client behind, one without a socket to judge by) are kept, their
    # oldest events skipped.
    assert hub.dropped == 1 and stalled.aborted and not reading.aborted
    assert [event async for event in stuck] == []
    assert hub.skipped == 2 * (len(events) - STREAM_QUEUE)
    assert all(len(sub.events) == STREAM_QUEUE for sub in hub.subscribers)
    # What was queued comes in one chunk, each event whole, the oldest first.
    kept = [event + b"\n\n" for event in (await anext(behind)).split(b"\n\n")[:-1]]
    assert len(kept) == STREAM_QUEUE
    last = gateway.cache.snapshot("s").seq
    assert [json.loads(event.split(b"data: ", 1)[1])["seq"] for event in kept] == \
        list(range(last - STREAM_QUEUE + 1, last + 1))
    assert kept[-1].startswith(b"event: reading\ndata: ")  # the newest
    assert json.loads(kept[-1].split(b"data: ", 1)[1])["seq"] == last
    hub.close()
    for stream in (behind, bare):
        await stream.aclose()
    assert hub.open == 0


@pytest.mark.anyio
async def test_an_overflow_before_the_first_chunk_keeps_where_each_sensor_stands() -> None:
    """The first events say where every sensor stands; a fast sensor that fills the
    queue before the stream sends them skips its own older readings, not them (a slow
    sensor's state would not come again before its next reading)."""
    config = config_from_dict({"buses": [{"name": "a", "port": "/dev/null",
                                          "protocol": "native", "sensors": [
                                              {"name": "fast", "series": "AH"},
                                              {"name": "slow", "series": "AH", "address": 1}]}]},
                              env={})
    gateway = Gateway(config)
    motion = Motion.from_seed(3)
    gateway.cache.publish("slow", motion.sample(0.0))
    hub = StreamHub(gateway)
    sub = hub.subscribe(None, _Peer(stalled=False))  # (the stream sends its head first)
    for n in range(STREAM_QUEUE + 10):
        gateway.cache.publish("fast", motion.sample(0.01 * n))
    chunk = await sub.next()
    assert chunk is not None
    events = [event for event in chunk.split(b"\n\n") if event]
    # (the first entry of the queue holds both sensors' events)
    assert len(events) == STREAM_QUEUE + 1 and hub.skipped >= 10
    named = [(e.split(b"\n", 1)[0], json.loads(e.split(b"data: ", 1)[1])["sensor"])
             for e in events]
    # the first events, whole: each sensor's state, then the newest of the fast one's
    assert named[:2] == [(b"event: status", "fast"), (b"event: reading", "slow")]
    assert {name for _, name in named[2:]} == {"fast"}
    last = gateway.cache.snapshot("fast").seq
    assert json.loads(events[-1].split(b"data: ", 1)[1])["seq"] == last
    hub.unsubscribe(sub)
    hub.close()
