"""The gateway's clients for the soak (``bench/soak.py``): the well-behaved ones that
keep every front end busy and time its answers, and the careless or hostile ones a
phase of the soak lets loose for a while.

Hostile clients connect from ``HOSTILE_HOST``, a second loopback address, as another
machine on the plant network would: a gateway that limits connections per address then
tells them apart from the well-behaved clients, which connect from 127.0.0.1.

Everything here speaks the wire protocols by hand (MBAP, HTTP/1.1, SSE) or through
paho-mqtt: a client library's own retries and pools would hide what the gateway did.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import socket
import struct
import termios
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTProtocolVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

HOST = "127.0.0.1"
HOSTILE_HOST = "127.0.0.2"
TIMEOUT = 5.0  # a well-behaved client gives up on an answer after this long
MBAP = struct.Struct(">HHHB")  # transaction id, protocol id, length, unit id


# ------------------------------------------------------------------ what was answered


@dataclass(frozen=True, slots=True)
class Answer:
    at: float  # time.monotonic() when the request went out
    latency: float | None  # seconds; None: no answer
    error: str = ""


class Record:
    """The answers one well-behaved client got, in time order."""

    def __init__(self) -> None:
        self.answers: list[Answer] = []

    def ok(self, at: float) -> None:
        self.answers.append(Answer(at, time.monotonic() - at))

    def failed(self, at: float, error: str) -> None:
        self.answers.append(Answer(at, None, error))

    def window(self, start: float, end: float) -> list[Answer]:
        return [a for a in self.answers if start <= a.at <= end]


# ------------------------------------------------------------------ Modbus TCP


def read_request(transaction: int, unit: int, start: int, count: int) -> bytes:
    """FC03 (read holding registers) in its MBAP header."""
    return MBAP.pack(transaction & 0xFFFF, 0, 6, unit) + struct.pack(">BHH", 3, start, count)


def write_request(transaction: int, unit: int, register: int, value: int) -> bytes:
    """FC06 (write single register) in its MBAP header."""
    return MBAP.pack(transaction & 0xFFFF, 0, 6, unit) + struct.pack(">BHH", 6, register, value)


async def read_answer(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    """One MBAP frame: (transaction id, PDU)."""
    transaction, _, length, _ = MBAP.unpack(await reader.readexactly(MBAP.size))
    return transaction, await reader.readexactly(length - 1)


async def modbus_once(port: int, unit: int = 1) -> bool:
    """A fresh connection reads the status block: does the server answer at all?"""
    try:
        async with asyncio.timeout(TIMEOUT):
            reader, writer = await asyncio.open_connection(HOST, port)
            try:
                writer.write(read_request(1, unit, 0, 9))
                transaction, pdu = await read_answer(reader)
            finally:
                writer.close()
        return transaction == 1 and pdu[0] == 3
    except (OSError, TimeoutError, asyncio.IncompleteReadError):
        return False


class ModbusPoller:
    """A SCADA-like poller on one long-lived connection: the status block and the
    float block of every unit in turn, ten requests a second."""

    def __init__(self, port: int, units: list[int], period: float = 0.1) -> None:
        self.port, self.units, self.period = port, units, period
        self.record = Record()
        self.reconnects = 0

    async def run(self) -> None:
        round_ = 0
        connection: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        while True:
            unit = self.units[round_ % len(self.units)]
            start, count = (0, 9) if round_ % 2 == 0 else (100, 32)
            at = time.monotonic()
            try:
                async with asyncio.timeout(TIMEOUT):
                    if connection is None:
                        connection = await asyncio.open_connection(HOST, self.port)
                        self.reconnects += 1
                    reader, writer = connection
                    writer.write(read_request(round_, unit, start, count))
                    transaction, _ = await read_answer(reader)
                if transaction != round_ & 0xFFFF:
                    raise ValueError(f"answer to transaction {transaction}, not {round_}")
                self.record.ok(at)
            except (OSError, TimeoutError, ValueError, asyncio.IncompleteReadError) as exc:
                self.record.failed(at, repr(exc))
                if connection is not None:
                    connection[1].close()
                connection = None
            round_ += 1
            await asyncio.sleep(max(0.0, at + self.period - time.monotonic()))


class ModbusWriter:
    """A SCADA that writes a setting now and then, on a long-lived connection: one
    FC06 write every ``period`` seconds.  ``on_sent`` is told of each write that left,
    so that the sensor's count of what it heard can be held against it: a gateway
    that sends a write twice (a retry after an answer lost to noise or a stall) makes
    the sensor hear more than was asked.  ``outcomes``: what came back, by kind (``ok``,
    ``exception 04`` for "unconfirmed: read the setting back", a failure's name)."""

    def __init__(self, port: int, unit: int, register: int, value: int,
                 on_sent: Callable[[], None], period: float = 3.0) -> None:
        self.port, self.unit, self.register, self.value = port, unit, register, value
        self.on_sent, self.period = on_sent, period
        self.outcomes: dict[str, int] = {}

    def _count(self, outcome: str) -> None:
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1

    async def run(self) -> None:
        transaction = 0
        connection: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None = None
        while True:
            at, transaction = time.monotonic(), transaction + 1
            try:
                async with asyncio.timeout(TIMEOUT + 5):  # a write waits for the sensor
                    if connection is None:
                        connection = await asyncio.open_connection(HOST, self.port)
                    reader, writer = connection
                    writer.write(write_request(transaction, self.unit, self.register,
                                               self.value))
                    self.on_sent()
                    _, pdu = await read_answer(reader)
                self._count("ok" if pdu[0] == 6 else f"exception {pdu[1]:02x}")
            except (OSError, TimeoutError, asyncio.IncompleteReadError) as exc:
                self._count(type(exc).__name__)
                if connection is not None:
                    connection[1].close()
                connection = None
            await asyncio.sleep(max(0.0, at + self.period - time.monotonic()))


class ModbusFlood:
    """Pipelines read requests and never reads an answer.

    Its receive buffer is made small, so the answers pile up at the gateway; a gateway
    that keeps reading must then keep the answers itself.  ``unread_bytes`` (at the
    end) is what the gateway left unread: in its socket's receive queue or still in
    this client's send queue."""

    def __init__(self, port: int, unit: int, requests: int = 200_000) -> None:
        self.port, self.unit, self.requests = port, unit, requests
        self.sent = 0
        self.closed_by_gateway = False
        self._stop = threading.Event()
        self._sock = socket.socket()
        self._thread = threading.Thread(target=self._run, name="modbus-flood", daemon=True)

    def start(self) -> None:
        sock = self._sock
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.bind((HOSTILE_HOST, 0))
        sock.settimeout(TIMEOUT)
        sock.connect((HOST, self.port))
        sock.settimeout(0.2)
        self._thread.start()

    def _run(self) -> None:
        data = b"".join(read_request(i, self.unit, 100, 32) for i in range(self.requests))
        view = memoryview(data)
        while self.sent < len(data) and not self._stop.is_set():
            try:
                self.sent += self._sock.send(view[self.sent: self.sent + 65536])
            except TimeoutError:
                continue  # the gateway is not reading: keep trying until told to stop
            except OSError:
                self.closed_by_gateway = True
                return

    def stop(self) -> dict[str, Any]:
        """Stop sending; then watch what the gateway leaves unread.  A gateway that
        stopped reading leaves the same bytes unread second after second; one still
        working through the backlog reads more each second, up to all of it."""
        self._stop.set()
        self._thread.join(5)
        unread, previous = self._unread(), -1
        deadline = time.monotonic() + 10
        while unread > 0 and unread != previous and time.monotonic() < deadline:
            time.sleep(1.0)
            previous, unread = unread, self._unread()
        self._sock.close()
        return {"requests_sent": self.sent // 12, "unread_bytes": unread,
                "stopped_reading": unread > 0 and unread == previous,
                "closed_by_gateway": self.closed_by_gateway}

    def _unread(self) -> int:
        return self._send_queue() + gateway_receive_queue(self.port, self._sock)

    def _send_queue(self) -> int:
        with contextlib.suppress(OSError):
            raw = fcntl.ioctl(self._sock.fileno(), termios.TIOCOUTQ, struct.pack("i", 0))
            return int(struct.unpack("i", raw)[0])
        return 0


def gateway_receive_queue(server_port: int, client: socket.socket) -> int:
    """Bytes waiting in the gateway's socket of this client's connection (the rx_queue
    column of /proc/net/tcp: the gateway has not read them)."""
    try:
        client_port = client.getsockname()[1]
        rows = Path("/proc/net/tcp").read_text().splitlines()[1:]
    except OSError:
        return 0
    for row in rows:
        fields = row.split()
        local, remote, queues = fields[1], fields[2], fields[4]
        if int(local.split(":")[1], 16) == server_port and \
                int(remote.split(":")[1], 16) == client_port:
            return int(queues.split(":")[1], 16)
    return 0


async def write_then_half_close(port: int, unit: int, register: int, value: int
                                ) -> tuple[bool, float, str]:
    """An FC06 write, then shutdown(SHUT_WR) at once, as ``nc -N`` does; the answer is
    still owed.  (answered, seconds, what came back)"""
    at = time.monotonic()
    try:
        async with asyncio.timeout(TIMEOUT + 5):  # a write waits for the sensor
            reader, writer = await asyncio.open_connection(
                HOST, port, local_addr=(HOSTILE_HOST, 0))
            try:
                writer.write(write_request(7, unit, register, value))
                await writer.drain()
                writer.write_eof()
                transaction, pdu = await read_answer(reader)
            finally:
                writer.close()
    except (OSError, TimeoutError, asyncio.IncompleteReadError) as exc:
        return False, time.monotonic() - at, repr(exc)
    return transaction == 7, time.monotonic() - at, pdu.hex()


# ------------------------------------------------------------------ many slow connections


@dataclass(slots=True)
class SwarmStats:
    opened: int = 0
    connect_failed: int = 0
    lifetimes: list[float] = field(default_factory=list)  # of those the gateway closed

    def to_json(self) -> dict[str, Any]:
        lives = sorted(self.lifetimes)
        return {"opened": self.opened, "connect_failed": self.connect_failed,
                "closed_by_gateway": len(lives),
                "closed_within_0.5_s": sum(life < 0.5 for life in lives),
                "median_life_s": round(lives[len(lives) // 2], 2) if lives else None}


Behaviour = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


class Swarm:
    """``count`` connections from ``HOSTILE_HOST``, each running ``behaviour`` until
    the gateway closes it; then it comes back a second later, as a slowloris does."""

    def __init__(self, port: int, count: int, behaviour: Behaviour) -> None:
        self.port, self.count, self.behaviour = port, count, behaviour
        self.stats = SwarmStats()
        self._tasks: list[asyncio.Task[None]] = []

    def start(self) -> None:
        self._tasks = [asyncio.create_task(self._one()) for _ in range(self.count)]

    async def stop(self) -> dict[str, Any]:
        await ended(self._tasks)
        return self.stats.to_json()

    async def _one(self) -> None:
        while True:
            try:
                reader, writer = await asyncio.open_connection(
                    HOST, self.port, local_addr=(HOSTILE_HOST, 0))
            except OSError:
                self.stats.connect_failed += 1
                await asyncio.sleep(1.0)
                continue
            self.stats.opened += 1
            opened = time.monotonic()
            try:
                await self.behaviour(reader, writer)
            except OSError:
                pass  # reset by the gateway: closed all the same
            finally:
                writer.close()
            self.stats.lifetimes.append(time.monotonic() - opened)
            await asyncio.sleep(1.0)


async def ended(tasks: list[asyncio.Task[Any]]) -> None:
    """Cancel ``tasks`` and wait until every one has ended, cancelling again each
    second one has not: a cancel can be lost where a client's own wait ends at the same
    moment (Python 3.11's ``wait_for``), and a client that carried on held the soak
    until its outer timeout (once, in a run of the test suite)."""
    while pending := [t for t in tasks if not t.done()]:
        for task in pending:
            task.cancel()
        await asyncio.wait(pending, timeout=1.0)
    for task in tasks:  # (their exceptions are theirs: retrieved, not raised)
        if not task.cancelled():
            task.exception()


async def _until_closed(reader: asyncio.StreamReader, seconds: float | None) -> bool:
    """Read (and drop) what comes for ``seconds``; True when the gateway closed."""
    try:
        async with asyncio.timeout(seconds):
            while await reader.read(4096):
                pass
            return True
    except TimeoutError:
        return False


def trickle(partial: bytes, period: float = 2.0) -> Behaviour:
    """Send ``partial`` one byte every ``period`` seconds, never the rest."""

    async def behave(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        for i in range(len(partial)):
            writer.write(partial[i: i + 1])
            if await _until_closed(reader, period):
                return
        await _until_closed(reader, None)

    return behave


async def idle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Connect and say nothing."""
    await _until_closed(reader, None)


class EndlessHeader:
    """A request whose one header line never ends, sent as fast as the gateway takes
    it; counts the status of each answer (``none``: closed without one)."""

    START = b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Long: "
    FILLER = b"a" * 65536

    def __init__(self) -> None:
        self.answers: dict[str, int] = {}
        self.sent = 0

    async def behave(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        first = asyncio.ensure_future(reader.read(64))
        try:
            writer.write(self.START)
            with contextlib.suppress(OSError):
                while not first.done():
                    writer.write(self.FILLER)
                    self.sent += len(self.FILLER)
                    await writer.drain()
                    # (drain returns without yielding while the transport is not paused:
                    # a gateway that reads as fast as this writes would starve the loop,
                    # the answer's read among it; the soak hung here once in three)
                    await asyncio.sleep(0)
            try:
                head = await asyncio.wait_for(first, TIMEOUT)
            except (OSError, TimeoutError):
                head = b""
        finally:
            first.cancel()
        status = head.split(b" ")[1].decode() if head.startswith(b"HTTP/1.1 ") else "none"
        self.answers[status] = self.answers.get(status, 0) + 1
        await _until_closed(reader, TIMEOUT)


#: 11 of the 12 bytes of an FC03 request: the frame is never complete.
PARTIAL_MBAP = read_request(1, 1, 0, 9)[:-1]
#: a request line and the start of a header that never ends
PARTIAL_HEADERS = b"GET /api/v1/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a" * 64


# ------------------------------------------------------------------ HTTP


def _dechunk(body: bytes) -> bytes:
    out = bytearray()
    while body:
        size_line, _, body = body.partition(b"\r\n")
        size = int(size_line.split(b";")[0] or b"0", 16)
        if size == 0:
            break
        out += body[:size]
        body = body[size + 2:]
    return bytes(out)


async def http_get(port: int, path: str, timeout: float = TIMEOUT) -> tuple[int, bytes]:
    """GET on a fresh connection (``Connection: close``): (status, body)."""
    async with asyncio.timeout(timeout):
        reader, writer = await asyncio.open_connection(HOST, port)
        try:
            writer.write(f"GET {path} HTTP/1.1\r\nHost: {HOST}:{port}\r\n"
                         "Connection: close\r\n\r\n".encode())
            data = await reader.read(-1)
        finally:
            writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    if not head.startswith(b"HTTP/1.1 "):
        raise ValueError(f"not an HTTP answer: {data[:40]!r}")
    if b"transfer-encoding: chunked" in head.lower():
        body = _dechunk(body)
    return int(head.split(b" ", 2)[1]), body


async def http_json(port: int, path: str) -> Any:
    status, body = await http_get(port, path)
    if status != 200:
        raise ValueError(f"GET {path}: {status}")
    return json.loads(body)


class HttpPoller:
    """REST polling: the sensor list four times a second, each sensor's reading in
    turn, and the metrics and bus statistics every 5 s, as a dashboard and a
    Prometheus scraper would."""

    def __init__(self, port: int, sensors: list[str], period: float = 0.25) -> None:
        self.port, self.sensors, self.period = port, sensors, period
        self.record = Record()

    def paths(self, round_: int) -> list[str]:
        paths = ["/api/v1/sensors",
                 f"/api/v1/sensors/{self.sensors[round_ % len(self.sensors)]}/reading"]
        if round_ % 20 == 0:
            paths += ["/metrics", "/api/v1/buses", "/api/v1/health"]
        return paths

    async def run(self) -> None:
        round_ = 0
        while True:
            started = time.monotonic()
            for path in self.paths(round_):
                at = time.monotonic()
                try:
                    status, body = await http_get(self.port, path)
                    if status >= 500 and b'"kind"' not in body:
                        # the gateway's own 503/504 (no reading, timeout) name their
                        # kind; a bare one is the server turning a client away
                        raise ValueError(f"GET {path}: {status}")
                    self.record.ok(at)
                except (OSError, TimeoutError, ValueError) as exc:
                    self.record.failed(at, f"{path}: {exc!r}")
            round_ += 1
            await asyncio.sleep(max(0.0, started + self.period - time.monotonic()))


class SseReader:
    """One client of ``/api/v1/stream`` that reads everything: events, sequence gaps
    within a connection, and drops (the stream ended without being asked to)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.events = 0
        self.gaps: list[tuple[float, str, int]] = []  # (when, sensor, samples missed)
        self.drops: list[tuple[float, str]] = []  # (when, why)
        self.last_event_at = 0.0
        self.silences: list[tuple[float, float]] = []  # (when it ended, seconds), > 0.1 s

    async def run(self) -> None:
        while True:
            try:
                await self._connection()
                self.drops.append((time.monotonic(), "the gateway ended the stream"))
            except (OSError, TimeoutError, ValueError, asyncio.IncompleteReadError) as exc:
                self.drops.append((time.monotonic(), repr(exc)))
            await asyncio.sleep(0.5)

    async def _connection(self) -> None:
        async with asyncio.timeout(TIMEOUT):
            reader, writer = await asyncio.open_connection(HOST, self.port)
        try:
            writer.write(f"GET /api/v1/stream HTTP/1.1\r\nHost: {HOST}\r\n\r\n".encode())
            async with asyncio.timeout(TIMEOUT):
                head = await reader.readuntil(b"\r\n\r\n")
            if b" 200 " not in head.split(b"\r\n")[0]:
                raise ValueError(f"stream refused: {head.splitlines()[0]!r}")
            await self._events(reader)
        finally:
            writer.close()

    async def _events(self, reader: asyncio.StreamReader) -> None:
        """The chunked body, cut into lines (a line may span chunks)."""
        last: dict[str, int] = {}
        pending = b""
        while True:
            async with asyncio.timeout(20):  # keep-alive comments come every 15 s
                size = int((await reader.readuntil(b"\r\n")).split(b";")[0], 16)
                chunk = await reader.readexactly(size + 2)
            if size == 0:
                return
            *lines, pending = (pending + chunk[:-2]).split(b"\n")
            for line in lines:
                if line.startswith(b"data: "):
                    self._event(json.loads(line[6:]), last)

    def longest_silence(self, start: float, end: float) -> float:
        """The longest time without an event that ended in [start, end], or still
        lasts at ``end``."""
        gaps = [seconds for t, seconds in self.silences if start <= t <= end]
        if self.last_event_at and self.last_event_at < end:
            gaps.append(end - max(self.last_event_at, start))
        return max(gaps, default=0.0)

    def _event(self, reading: dict[str, Any], last: dict[str, int]) -> None:
        now = time.monotonic()
        self.events += 1
        if self.last_event_at and now - self.last_event_at > 0.1:
            self.silences.append((now, now - self.last_event_at))
        self.last_event_at = now
        name, seq = reading["sensor"], reading["seq"]
        if name in last and seq > last[name] + 1:
            self.gaps.append((now, name, seq - last[name] - 1))
        last[name] = max(seq, last.get(name, seq))


# ------------------------------------------------------------------ MQTT


def mqtt_client(version: MQTTProtocolVersion = paho.MQTTv311,
                client_id: str = "") -> paho.Client:
    return paho.Client(CallbackAPIVersion.VERSION2, client_id=client_id, protocol=version)


class MqttWatcher:
    """The well-behaved subscriber: every state message (and its ``seq`` gaps), the
    gateway's status, and command results.  paho reconnects it by itself, at most a
    second after the broker is back; its callbacks run on paho's thread."""

    def __init__(self, port: int, base: str) -> None:
        self.base = base
        self.lock = threading.Lock()
        self.states = 0
        self.bad_states = 0
        self.last_state_at = 0.0
        self.last_seq: dict[str, int] = {}
        self.gaps: list[tuple[float, str, int]] = []  # (when, sensor, samples missed)
        self.status: list[tuple[float, str]] = []  # (when, payload) of the gateway's status
        self.results: list[tuple[float, str, bytes]] = []  # the latest command results
        self._waiting: dict[str, tuple[asyncio.AbstractEventLoop, asyncio.Future[float]]] = {}
        self.client = mqtt_client(client_id="soak-watcher")
        self.client.reconnect_delay_set(1, 1)  # paho takes whole seconds
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message
        self.client.connect_async(HOST, port)
        self.client.loop_start()

    def _on_connect(self, client: paho.Client, *_: Any) -> None:
        for leaf in ("status", "+/state", "+/cmd/+/result"):
            client.subscribe(f"{self.base}/{leaf}", qos=0)

    def _on_message(self, client: paho.Client, userdata: Any,
                    message: paho.MQTTMessage) -> None:
        now = time.monotonic()
        topic = message.topic
        with self.lock:
            if topic == f"{self.base}/status":
                self.status.append((now, message.payload.decode(errors="replace")))
            elif topic.endswith("/state"):
                # paho's thread would die of an exception here; a bad payload is counted
                try:
                    self._state(now, bytes(message.payload))
                except (ValueError, KeyError, TypeError):
                    self.bad_states += 1
            elif topic.endswith("/result"):
                self.results.append((now, topic, bytes(message.payload)))
                del self.results[:-1000]
                if topic in self._waiting:
                    loop, future = self._waiting.pop(topic)
                    loop.call_soon_threadsafe(_resolve, future, now)

    def _state(self, now: float, payload: bytes) -> None:
        reading = json.loads(payload)
        name, seq = reading["sensor"], reading["seq"]
        self.states += 1
        self.last_state_at = now
        last = self.last_seq.get(name)
        if last is not None and seq > last + 1:
            self.gaps.append((now, name, seq - last - 1))
        self.last_seq[name] = max(seq, last if last is not None else seq)

    def online_since(self, since: float) -> bool:
        """The gateway said "online" after ``since`` and a state came after that."""
        with self.lock:
            said = [t for t, text in self.status if t >= since and text == "online"]
            return bool(said) and self.last_state_at > said[0]

    def expect(self, topic: str) -> asyncio.Future[float]:
        """A future set to the arrival time of the next message on ``topic``."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[float] = loop.create_future()
        with self.lock:
            self._waiting[topic] = (loop, future)
        return future

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def _resolve(future: asyncio.Future[float], value: float) -> None:
    if not future.done():
        future.set_result(value)


class MqttCommander:
    """A well-behaved MQTT client that asks a sensor for its settings once a second
    and times the result (the same topic plus ``/result``).  ``{}``: an empty payload
    is not a command (it is how a retained message is cleared)."""

    def __init__(self, watcher: MqttWatcher, sensor: str, period: float = 1.0) -> None:
        self.watcher, self.period = watcher, period
        self.topic = f"{watcher.base}/{sensor}/cmd/read_settings"
        self.record = Record()

    async def run(self) -> None:
        while True:
            at = time.monotonic()
            await self.ask(at)
            await asyncio.sleep(max(0.0, at + self.period - time.monotonic()))

    async def ask(self, at: float) -> None:
        future = self.watcher.expect(f"{self.topic}/result")
        info = self.watcher.client.publish(self.topic, b"{}", qos=1)
        if info.rc != paho.MQTT_ERR_SUCCESS:
            self.record.failed(at, f"publish: {paho.error_string(info.rc)}")
            return
        try:
            arrived = await asyncio.wait_for(future, TIMEOUT)
        except TimeoutError:
            self.record.failed(at, "no result")
            return
        self.record.answers.append(Answer(at, arrived - at))


def publish_hostile(port: int, messages: list[tuple[str, bytes, bool, Properties | None]]
                    ) -> list[str]:
    """Publish ``(topic, payload, retain, properties)`` with MQTT 5 at QoS 1 from a
    client of its own; what went wrong on the way (the broker may refuse)."""
    client = mqtt_client(paho.MQTTv5)
    problems = []
    client.connect(HOST, port)
    client.loop_start()
    try:
        for topic, payload, retain, properties in messages:
            try:
                info = client.publish(topic, payload, qos=1, retain=retain,
                                      properties=properties)
                info.wait_for_publish(TIMEOUT)
                if not info.is_published():
                    problems.append(f"{topic[:40]}: not acknowledged by the broker")
            except (ValueError, RuntimeError) as exc:
                problems.append(f"{topic[:40]}: {exc}")
    finally:
        client.disconnect()
        client.loop_stop()
    return problems


class Listener:
    """An MQTT 5 client that records, on ``topics``, every message that carries the
    correlation data ``correlation`` (a command result for the asker; the gateway's own
    messages carry none)."""

    def __init__(self, port: int, topics: list[str], correlation: bytes) -> None:
        self.correlation = correlation
        self.got: list[str] = []
        subscribed = threading.Event()
        self.client = mqtt_client(paho.MQTTv5)
        self.client.on_connect = lambda c, *_: c.subscribe([(t, 1) for t in topics])
        self.client.on_subscribe = lambda *_: subscribed.set()
        self.client.on_message = self._on_message
        self.client.connect(HOST, port)
        self.client.loop_start()
        if not subscribed.wait(TIMEOUT):
            self.close()
            raise RuntimeError("the listener got no SUBACK")

    def _on_message(self, client: paho.Client, userdata: Any,
                    message: paho.MQTTMessage) -> None:
        if getattr(message.properties, "CorrelationData", None) == self.correlation:
            self.got.append(message.topic)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def response_topic(topic: str) -> Properties:
    properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]
    properties.ResponseTopic = topic
    properties.CorrelationData = b"soak"
    return properties
