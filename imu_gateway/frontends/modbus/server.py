"""The Modbus TCP server: the register map (docs/register-map.md) for PLCs and SCADA.

Why not pymodbus's server: measured on pymodbus 3.16.1, it answers only the first of
several requests that arrive in one TCP segment, answers an unknown unit id with
exception 04 (not 0A) and a read of 126 registers with function code 0x80 (not
exception 03).  Those are the server's framing and dispatch, so this module owns
them: the MBAP header over an ``asyncio.Protocol``, every request of a segment
answered in order, and the exceptions docs/register-map.md lists.  pymodbus still
decodes the write PDUs and encodes the write and exception answers.  The hot path, a
read, is a bounds check and a slice of the sensor's byte image (``map.py``):
a read never waits for the serial bus, so a hundred clients cost the bus nothing.

Writes to the command registers become commands; the answer is sent after the sensor
acknowledged.  A sensor with ``raw_unit_id`` also answers on that unit with its own
registers, passed through the bus master unchanged.

Careless and hostile clients (docs/reliability.md).  A client's answers that it does
not read stop its requests from being read (``WRITE_BOUND``); a frame must be whole
within ``FRAME_DEADLINE_S``; a full server, or a client address at its limit, closes
the longest-idle connection to make room for the newcomer (as the Modbus Messaging
Implementation Guide advises), so that clients who only hold sockets cannot lock SCADA
out; every request that came before a client's FIN is answered; warnings about
peers are rate-limited.

Modbus/TCP Security (``modbus.tls``, ``tls.py``): a second listening socket whose
connections are this module's ``_Connection``, upgraded to TLS by ``loop.start_tls``
once admitted, so all of the above holds there too; each request is first checked
against the rights of the role in the client's certificate (refused: exception 01).
The port listens in plain TCP and does the handshake itself, rather than asyncio's
``create_server(ssl=...)``, because a connection must be counted from its accept:
one whose handshake is in progress holds a socket, and the limits, ``allow_from`` and
the room-for-newcomers rule must reach it, or clients that connect and never
handshake take every descriptor of the process (every port and file fails then).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import os
import socket
import ssl
import struct
import time
from collections import Counter
from collections.abc import Awaitable
from typing import Any

from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import WriteMultipleRegistersResponse

from ...alarms import AlarmState
from ...cache import ALL_EVENTS, EventKind, Snapshot
from ...config import ModbusConfig, SensorConfig
from ...config.schema import ModbusTlsConfig
from ...errors import KINDS, ErrorKind, RequestFailed, StartupError
from ...modbus_codes import (
    DEVICE_FAILURE,
    GATEWAY_PATH,
    ILLEGAL_ADDRESS,
    ILLEGAL_FUNCTION,
    ILLEGAL_VALUE,
    READ_HOLDING,
    READ_INPUT,
    TARGET_FAILED,
    WRITE_MULTIPLE,
    WRITE_SINGLE,
)
from ...stats import FrontendCounts
from ...supervise import Frontend, PeerLog
from ..common import GatewayLike
from . import alarms as alarm_bits
from . import ident
from . import map as mm
from . import tls as modbus_tls

log = logging.getLogger("imu_gateway.modbus")

MAX_READ, MAX_WRITE = 125, 123
MBAP = struct.Struct(">HHHB")  # transaction id, protocol id, length, unit id
MAX_LENGTH = 254  # unit id + the longest PDU (253 bytes)
BACKLOG_BYTES = 16 * 1024  # stop reading a client that sends faster than it is answered
WRITE_BOUND = 64 * 1024  # answers a client has not read: beyond this its requests wait
SEND_BUFFER = 64 * 1024  # bytes of kernel send buffer per connection
FRAME_DEADLINE_S = 5.0  # a started frame must be whole within this (a trickle is closed)
HOUSEKEEPING_S = 1.0  # how often the rate-limited peer warnings are summed up

def exception_for(kind: ErrorKind) -> int:
    """How a failed request is told to a Modbus client (docs/modbus-tcp.md): the
    kind's row of ``imu_gateway.errors.KINDS``."""
    return KINDS[kind].modbus or TARGET_FAILED


def exception(function: int, code: int) -> bytes:
    return _pdu(ExceptionResponse(function, code))


def _pdu(pdu: ModbusPDU) -> bytes:
    return bytes([pdu.function_code]) + pdu.encode()


class _Unit:
    """One unit id of the map: a sensor, its byte image and its alarms' bits."""

    def __init__(self, sensor: SensorConfig, protocol: Any,
                 alarms: list[AlarmState]) -> None:
        self.sensor = sensor
        self.image = mm.SensorImage(sensor.series, protocol, sensor.address,
                                    sensor.stale_after_ms)
        self.alarms = alarm_bits.UnitAlarms(alarms)
        self.image.set_alarms(self.alarms.registers())
        if len(alarms) > alarm_bits.MASK_BITS:
            log.warning("Modbus TCP: sensor %s has %d alarms; registers %d-%d carry the "
                        "first %d, its discrete inputs and coils all of them", sensor.name,
                        len(alarms), mm.ALARM_BASE, mm.BLOCKS[-2].stop - 1,
                        alarm_bits.MASK_BITS)

    def alarm_changed(self, state: AlarmState) -> None:
        self.alarms.update(state)
        self.image.set_alarms(self.alarms.registers())


class ModbusTcpServer(Frontend):
    name = "modbus"

    def __init__(self, gateway: GatewayLike, config: ModbusConfig) -> None:
        super().__init__()
        self.gateway = gateway
        self.config = config
        self.sensors_changed()
        self._decoder = DecodePDU(is_server=True)
        self.connections: set[_Connection] = set()
        self.counts: Counter[str] = Counter()
        self._server: asyncio.Server | None = None  # the plain port
        self._tls_server: asyncio.Server | None = None
        self.tls_context: ssl.SSLContext | None = None  # the TLS port's, once it listens
        self.peers = PeerLog(log)
        self._housekeeping: asyncio.TimerHandle | None = None
        # ALARM events too: the alarms' bits change only at a transition.  Not prompt:
        # each request brings the images up to date first (``handle``).
        gateway.cache.subscribe(self._on_cache_event, self.fail, kinds=ALL_EVENTS,
                                prompt=False)

    def sensors_changed(self) -> None:
        """The unit map made from the gateway's sensors (at start, and at once after a
        reload changed them: the connections stay)."""
        gateway = self.gateway
        protocols = {s.name: b.protocol for b, s in gateway.config.iter_sensors()}
        self._protocols = protocols
        alarms: dict[str, list[AlarmState]] = {name: [] for name in gateway.sensors}
        for state in gateway.alarm_states():  # (in order: the communication alarm last)
            alarms[state.sensor].append(state)
        self.units = {s.unit_id: _Unit(s, protocols[s.name], alarms[s.name])
                      for s in gateway.sensors.values()}
        self._by_name = {u.sensor.name: u for u in self.units.values()}
        self.raw_units = {s.raw_unit_id: s.name for s in gateway.sensors.values()
                          if s.raw_unit_id is not None}
        for name, unit in self._by_name.items():
            unit.image.set_reading(gateway.cache.snapshot(name).reading)

    def _on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        unit = self._by_name.get(snap.name)  # (None: a sensor a reload just removed)
        if unit is None:
            return
        if kind is EventKind.READING:
            unit.image.set_reading(snap.reading)
        elif kind is EventKind.ALARM and snap.alarm is not None:
            unit.alarm_changed(snap.alarm.state)

    async def start(self) -> None:
        """Listen on the plain port and the TLS port, those configured; raises
        ``OSError`` when the plain address cannot be bound, ``StartupError`` when the
        TLS port cannot be opened (its address, or its certificate files)."""
        listen, tls = self.config.listen, self.config.tls
        if listen is not None:
            self._server = await asyncio.get_running_loop().create_server(
                lambda: _Connection(self), listen.host, listen.port)
            log.info("Modbus TCP on %s:%d, units %s", listen.host, self.port, self._unit_ids)
        if tls is not None:
            try:
                self._tls_server = await self._start_tls(tls)
            except BaseException:
                await self.stop()  # not half started: the plain port closes again
                raise
            log.info("Modbus/TCP Security on %s:%d, units %s, roles %s", tls.listen.host,
                     self.tls_port, self._unit_ids, ", ".join(tls.roles) or "none")
        self._tidy()

    @property
    def _unit_ids(self) -> list[int]:
        return sorted(self.units) + sorted(self.raw_units)

    async def _start_tls(self, tls: ModbusTlsConfig) -> asyncio.Server:
        # Plain TCP: each _Connection upgrades itself once admitted (see the docstring).
        self.tls_context = modbus_tls.server_context(tls, self._refused_handshake)
        try:
            return await asyncio.get_running_loop().create_server(
                lambda: _Connection(self, tls), tls.listen.host, tls.listen.port)
        except OSError as exc:
            reason = os.strerror(exc.errno) if exc.errno else str(exc)
            raise StartupError(f"modbus.tls.listen {tls.listen}: {reason}") from None

    def _refused_handshake(self, exc: ssl.SSLError) -> None:
        self.counts["refused_handshake"] += 1
        self.peers.warning("refused_handshake", "Modbus/TCP Security: refused a client "
                           "at the TLS handshake: %s", modbus_tls.handshake_problem(exc))

    def _tidy(self) -> None:
        self.peers.flush_due()
        self._housekeeping = asyncio.get_running_loop().call_later(HOUSEKEEPING_S,
                                                                   self._tidy)

    def admit(self, newcomer: _Connection) -> None:
        """Make room for a new connection: close the longest-idle one of its address,
        or of all, when either is at its limit (an unfinished TLS handshake first)."""
        config = self.config
        for why, limit in (("per_address", config.max_connections_per_address),
                           ("limit", config.max_connections)):
            crowd = [c for c in self.connections
                     if why == "limit" or c.address == newcomer.address]
            if len(crowd) < limit:
                continue
            victim = min(crowd, key=_Connection.idle_rank)
            self.counts[f"evicted_{why}"] += 1
            self.peers.warning(f"evicted_{why}", "Modbus TCP: closed %s, %s, to make room "
                               "for %s (%s)", victim.peer, "idle longest" if victim.ready
                               else "its TLS handshake unfinished", newcomer.peer,
                               "max_connections_per_address" if why == "per_address"
                               else "max_connections")
            victim.evict()

    @property
    def listening(self) -> bool:
        return self._server is not None or self._tls_server is not None

    def stats(self) -> FrontendCounts:
        ready = sum(c.ready for c in self.connections)
        return {"clients": ready, "requests": self.counts["requests"], **self.counts,
                "handshaking": len(self.connections) - ready}

    @property
    def port(self) -> int:
        """The plain port's number (useful when ``listen`` asked for port 0)."""
        assert self._server is not None
        return int(self._server.sockets[0].getsockname()[1])

    @property
    def tls_port(self) -> int:
        assert self._tls_server is not None
        return int(self._tls_server.sockets[0].getsockname()[1])

    async def stop(self) -> None:
        if self._housekeeping is not None:
            self._housekeeping.cancel()
        self.peers.flush()
        servers = [s for s in (self._server, self._tls_server) if s is not None]
        self._server = self._tls_server = None
        for server in servers:
            server.close()
        handshakes = [c.handshake for c in self.connections if c.handshake is not None]
        for connection in list(self.connections):
            connection.close()
        for server in servers:
            await server.wait_closed()
        await asyncio.gather(*handshakes, return_exceptions=True)  # (they end at once)

    # ------------------------------------------------------------ requests

    def handle(self, unit_id: int, pdu: bytes, writes: bool,
               who: str = "modbus") -> bytes | Awaitable[bytes]:
        """The answer PDU to a request PDU: at once for reads, later for writes.
        ``writes``: whether the connection may write (``allow_writes``, or on the TLS
        port true, its role's rights having been checked); ``who``: the client, as an
        acknowledgement's journal line names it."""
        function = pdu[0]
        self.counts["requests"] += 1
        self.gateway.cache.catch_up()  # (the images are the cache's, however lazy)
        if function == ident.FUNCTION:  # answered here, raw units too: no bus traffic
            return self._identify(unit_id, pdu)
        if unit_id in self.raw_units:
            return self._passthrough(self.raw_units[unit_id], pdu, writes)
        unit = self.units.get(unit_id)
        if unit is None:
            if unit_id == mm.DIAG_UNIT:  # sensor unit ids are 1-247
                return self._diagnostics(pdu)
            return exception(function, GATEWAY_PATH)
        if function in (READ_HOLDING, READ_INPUT):
            return self._read(unit, pdu)
        if function in (alarm_bits.READ_COILS, alarm_bits.READ_DISCRETE):
            return alarm_bits.read(unit.alarms, pdu)
        if function == alarm_bits.WRITE_COIL:
            return self._acknowledge(unit, pdu, who) if writes \
                else exception(function, ILLEGAL_FUNCTION)
        if function in (WRITE_SINGLE, WRITE_MULTIPLE):
            problem = self._check_write(pdu, writes)
            if problem:
                return exception(function, problem)
            return self._write(unit, pdu)
        return exception(function, ILLEGAL_FUNCTION)

    def _read(self, unit: _Unit, pdu: bytes) -> bytes:
        function = pdu[0]
        span = _read_span(pdu)
        if span is None:
            return exception(function, ILLEGAL_VALUE)
        start, count = span
        block = mm.block_of(start, count)
        if block is None:
            return exception(function, ILLEGAL_ADDRESS)
        image = unit.image
        if block.start == mm.ALARM_BASE:
            pass  # kept up to date at each transition
        elif block.start == 0 or block.start == mm.COMMAND_BASE:
            snap = self.gateway.cache.snapshot(unit.sensor.name)
            if block.start == 0:
                image.refresh_status(snap)
            else:
                image.refresh_commands(snap, self.gateway.cache.settings(unit.sensor.name))
        elif not image.has_reading:
            return exception(function, TARGET_FAILED)  # no reading yet
        return bytes((function, 2 * count)) + image.words[2 * start: 2 * (start + count)]

    def _acknowledge(self, unit: _Unit, pdu: bytes, who: str) -> bytes:
        """FC 05: acknowledge the alarm at the coil's address (``alarms.write``)."""
        def acknowledge(alarm: str) -> AlarmState:
            state = self.gateway.acknowledge(unit.sensor.name, alarm, who)
            self.counts["acknowledged"] += 1
            return state

        try:
            return alarm_bits.write(unit.alarms, pdu, acknowledge)
        except RequestFailed as exc:  # nothing to acknowledge: 03 (errors.KINDS)
            return exception(pdu[0], exception_for(exc.kind))

    def _identify(self, unit_id: int, pdu: bytes) -> bytes:
        """Read Device Identification: a sensor's unit (its raw unit too) says what
        the sensor is; unit 255 what the gateway is (``ident.py``)."""
        unit = self.units.get(unit_id)
        raw = self.raw_units.get(unit_id)
        if unit is None and raw is not None:
            unit = self._by_name[raw]
        if unit is not None:
            s = unit.sensor
            who = ident.Identity(s.series, self._protocols[s.name], s.name)
        elif unit_id == mm.DIAG_UNIT:
            who = ident.Identity(None, None, self.gateway.config.gateway_id)
        else:
            return exception(pdu[0], GATEWAY_PATH)
        return ident.answer(pdu, who)

    def _diagnostics(self, pdu: bytes) -> bytes:
        function = pdu[0]
        if function not in (READ_HOLDING, READ_INPUT):
            return exception(function, ILLEGAL_FUNCTION)
        span = _read_span(pdu)
        if span is None:
            return exception(function, ILLEGAL_VALUE)
        start, count = span
        image = mm.diagnostics_image(self.gateway.stats())
        if 2 * (start + count) > len(image):
            return exception(function, ILLEGAL_ADDRESS)
        return bytes((function, 2 * count)) + image[2 * start: 2 * (start + count)]

    def _check_write(self, pdu: bytes, writes: bool) -> int:
        """An exception code for a write that must be refused before decoding, or 0."""
        if not writes:
            return ILLEGAL_FUNCTION
        if pdu[0] == WRITE_SINGLE:
            return 0 if len(pdu) == 5 else ILLEGAL_VALUE
        if len(pdu) < 6:
            return ILLEGAL_VALUE
        count, byte_count = struct.unpack_from(">HB", pdu, 3)
        if not 1 <= count <= MAX_WRITE or byte_count != 2 * count or len(pdu) != 6 + byte_count:
            return ILLEGAL_VALUE
        return 0

    async def _write(self, unit: _Unit, pdu: bytes) -> bytes:
        function = pdu[0]
        request = self._decoder.decode(pdu)
        if request is None:
            return exception(function, ILLEGAL_VALUE)
        address, words = request.address, list(request.registers)
        reg = mm.BY_ADDRESS.get(address)
        if reg is None and mm.inside_a_value(address):
            return exception(function, ILLEGAL_VALUE)  # starts at a float's second half
        if reg is None or reg.command is None:
            return exception(function, ILLEGAL_ADDRESS)
        if len(words) != reg.type.words:
            return exception(function, ILLEGAL_VALUE)  # half a float, or two commands
        if unit.sensor.series not in reg.series:
            return exception(function, ILLEGAL_ADDRESS)
        args = mm.command_args(mm.COMMANDS[address], words)
        if args is None:
            return exception(function, ILLEGAL_VALUE)
        self.counts["writes"] += 1
        result = await self.gateway.command(unit.sensor.name, reg.command, args)
        if not result.ok:
            assert result.kind is not None
            return exception(function, exception_for(result.kind))
        if function == WRITE_SINGLE:
            return pdu  # the answer to FC06 is the request
        return _pdu(WriteMultipleRegistersResponse(address=address, count=len(words)))

    async def _passthrough(self, sensor: str, pdu: bytes, writes: bool) -> bytes:
        function = pdu[0]
        if function in (READ_HOLDING, READ_INPUT):
            if _read_span(pdu) is None:
                return exception(function, ILLEGAL_VALUE)
        elif function in (WRITE_SINGLE, WRITE_MULTIPLE):
            if problem := self._check_write(pdu, writes):
                return exception(function, problem)
        else:
            return exception(function, ILLEGAL_FUNCTION)
        self.counts["passthrough"] += 1
        try:
            return await self.gateway.passthrough(sensor, pdu)
        except RequestFailed as exc:
            return exception(function, exception_for(exc.kind))


def _read_span(pdu: bytes) -> tuple[int, int] | None:
    """(start, count) of an FC03/FC04 request, or None when it is malformed or asks
    for a quantity outside 1-125 (exception 03)."""
    if len(pdu) != 5:
        return None
    start, count = struct.unpack_from(">HH", pdu, 1)
    return (start, count) if 1 <= count <= MAX_READ else None


class _Connection(asyncio.Protocol):
    """One client: MBAP framing, requests answered in order, deadlines, back-pressure;
    on the TLS port (``tls``), the handshake first, then each request checked against
    its role's rights."""

    def __init__(self, server: ModbusTcpServer, tls: ModbusTlsConfig | None = None) -> None:
        self.server = server
        self.tls = tls
        self.grant: modbus_tls.Grant | None = None  # TLS: what the role may do
        self.writes = server.config.allow_writes if tls is None else True
        self.refused = 0  # TLS: requests refused for lack of a right
        self.transport: asyncio.Transport | None = None  # the one requests are served on
        self.tcp: asyncio.Transport | None = None  # TLS: the socket, while it handshakes
        self.handshake: asyncio.Task[None] | None = None
        self.ready = False  # accepted and (TLS) handshaken: requests are served
        self.buffer = bytearray()
        self.waiting = False  # a write or pass-through is in progress: later ones queue
        self.blocked = False  # the client does not read its answers (WRITE_BOUND)
        self.ended = False  # the client sent FIN: answer what came, then close
        self.idle: asyncio.TimerHandle | None = None
        self.frame_timer: asyncio.TimerHandle | None = None
        self.peer = "?"
        self.address = "?"
        self.requests = 0
        self.last_request = time.monotonic()  # or the connect, before the first

    @property
    def who(self) -> str:
        """The client as the alarm journal names who acknowledged (REST's form):
        ``modbus 10.0.0.5``; on the TLS port its certificate's subject first,
        ``CN=hmi-1 (modbus 10.0.0.5)``."""
        where = f"modbus {self.address}"
        return where if self.grant is None else f"{self.grant.who} ({where})"

    def idle_rank(self) -> tuple[bool, bool, float]:
        """Sorts first the connection to close for room: an unfinished TLS handshake,
        then one that never completed a request (a trickle, a held socket), then the
        one quiet longest (the oldest first, among equals)."""
        return (self.ready, self.requests > 0, self.last_request)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        """A TCP connection accepted (on the TLS port too: before its handshake)."""
        assert isinstance(transport, asyncio.Transport)
        peer = transport.get_extra_info("peername") or ("?", 0)
        self.peer, self.address = f"{peer[0]}:{peer[1]}", str(peer[0])
        server = self.server
        if not server.config.allows(self.address):
            server.counts["refused_address"] += 1
            server.peers.warning("refused_address", "Modbus TCP: refused %s (not in "
                                 "allow_from)", self.peer)
            transport.abort()
            return
        server.admit(self)
        sock = transport.get_extra_info("socket")
        if sock is not None:
            # The kernel's own send buffer grows to megabytes for a client that does
            # not read; answered into it, a flood of requests holds the loop for a
            # third of a second before WRITE_BOUND is reached.  A fixed one does not.
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        server.connections.add(self)  # a handshake in progress takes its place too
        server.counts["connections"] += 1
        if self.tls is None:
            self._serve(transport)
            return
        self.tcp = transport
        transport.pause_reading()  # the ClientHello is the TLS layer's, not data_received's
        self.handshake = asyncio.ensure_future(self._handshake(transport, self.tls))

    async def _handshake(self, tcp: asyncio.Transport, tls: ModbusTlsConfig) -> None:
        """Upgrade to TLS, then serve; a failed handshake is logged by the context's
        hook (``modbus_tls.server_context``), a late one here."""
        server = self.server
        assert server.tls_context is not None
        transport: asyncio.Transport | None = None
        try:
            transport = await asyncio.get_running_loop().start_tls(
                tcp, self, server.tls_context, server_side=True,
                ssl_handshake_timeout=modbus_tls.HANDSHAKE_TIMEOUT_S,
                ssl_shutdown_timeout=FRAME_DEADLINE_S)
        except ConnectionAbortedError:  # asyncio's handshake deadline
            server.counts["handshake_timeouts"] += 1
            server.peers.warning("handshake_timeouts", "Modbus/TCP Security: closed %s: "
                                 "no TLS handshake within %g s", self.peer,
                                 modbus_tls.HANDSHAKE_TIMEOUT_S)
        except OSError:  # refused (logged by the hook), or the client went away
            pass
        self.tcp = None
        if transport is None or self not in server.connections:  # lost, or evicted
            server.connections.discard(self)
            if transport is not None:
                transport.abort()
            return
        self._serve(transport)

    def _serve(self, transport: asyncio.Transport) -> None:
        """Start serving requests: at once on the plain port, after the handshake on
        the TLS port (where what came with the handshake's last flight is waiting)."""
        self.transport, self.ready = transport, True
        transport.set_write_buffer_limits(high=WRITE_BOUND)
        if self.tls is not None:
            self._take_role(transport, self.tls)
        self._watch_idle()
        if self.buffer or self.ended:
            self._answer_what_is_complete()

    def _take_role(self, transport: asyncio.Transport, tls: ModbusTlsConfig) -> None:
        grant = self.grant = modbus_tls.grant_of(transport, tls)
        if grant.note:
            self.server.peers.warning("tls_role", "Modbus/TCP Security: %s (%s): %s",
                                      self.peer, grant.who, grant.note)
        log.debug("Modbus/TCP Security: %s (%s), role %s: %s", self.peer, grant.who,
                  grant.role, ", ".join(sorted(grant.rights)) or "no rights")

    def _refuses(self, unit: int, function: int) -> bool:
        """Whether the connection's role lacks the right the request needs (TLS)."""
        grant = self.grant
        if grant is None:
            return False
        right = modbus_tls.right_needed(function, unit in self.server.raw_units)
        if right in grant.rights:
            return False
        self.server.counts["refused_role"] += 1
        self.refused += 1
        if self.refused == 1:  # once a connection (and rate-limited across them)
            self.server.peers.warning(
                "refused_role", "Modbus/TCP Security: refused FC%02d to unit %d from %s "
                "(%s, role %s, rights: %s; it needs %s): exception 01; further refusals "
                "on this connection are only counted", function, unit, self.peer,
                grant.who, grant.role, ", ".join(sorted(grant.rights)) or "none",
                right or "a function nobody may use")
        return True

    def connection_lost(self, exc: Exception | None) -> None:
        self.server.connections.discard(self)
        for timer in (self.idle, self.frame_timer):
            if timer is not None:
                timer.cancel()

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
        elif self.tcp is not None:  # nothing to say to a client that is still handshaking
            self.tcp.abort()

    def evict(self) -> None:
        self.server.connections.discard(self)  # its room is taken now
        transport = self.transport or self.tcp
        if transport is not None:
            transport.abort()

    def _watch_idle(self) -> None:
        """Close the connection once ``last_request`` is ``idle_timeout_s`` old.  One
        timer, re-armed for the rest of the time when it fires: a busy client's
        requests only set ``last_request``, they cost no timer each."""
        timeout = self.server.config.idle_timeout_s
        if not timeout:
            return
        left = self.last_request + timeout - time.monotonic()
        if left > 0:
            self.idle = asyncio.get_running_loop().call_later(left, self._watch_idle)
        else:
            self._time_out("idle_closed")

    def _time_out(self, why: str) -> None:
        self.server.counts[why] += 1
        if self.transport is not None:
            self.transport.abort()

    # ------------------------------------------------------------ flow control

    def pause_writing(self) -> None:
        """The client's unread answers passed ``WRITE_BOUND``: read no more of it."""
        if self.transport is None:  # (TLS: its handshake's own writes; no answer yet)
            return
        self.blocked = True
        self.server.counts["paused_unread"] += 1
        self.transport.pause_reading()

    def resume_writing(self) -> None:
        self.blocked = False
        if self.transport is not None:
            self._answer_what_is_complete()

    # TLS: asyncio hands over what came with the handshake's last flight before
    # start_tls returns; it waits in the buffer until _serve.

    def eof_received(self) -> bool:
        """The client is done sending; what it sent before is still answered."""
        self.ended = True
        if self.transport is not None:
            self._answer_what_is_complete()
        # The transport stays open for the answers (_finish_if_ended closes), except on
        # TLS: asyncio closes after the client's close_notify whatever this says, and
        # logs a warning for each True.
        return self.tls is None

    def data_received(self, data: bytes) -> None:
        self.buffer += data
        if self.transport is not None:
            self._answer_what_is_complete()

    # ------------------------------------------------------------ requests

    def _answer_what_is_complete(self) -> None:
        transport = self.transport
        assert transport is not None
        buffer = self.buffer
        while not (self.waiting or self.blocked) and len(buffer) >= MBAP.size:
            transaction, protocol, length, unit = MBAP.unpack_from(buffer)
            if protocol != 0 or not 2 <= length <= MAX_LENGTH:
                # Not Modbus, or framing lost: nothing after this can be trusted.
                self.server.counts["bad_mbap"] += 1
                self.server.peers.warning("bad_mbap", "Modbus TCP: closing %s: MBAP "
                                          "protocol id %d, length %d", self.peer, protocol,
                                          length)
                transport.abort()
                buffer.clear()
                return
            if len(buffer) < 6 + length:
                break
            pdu = bytes(buffer[MBAP.size: 6 + length])
            del buffer[: 6 + length]
            self._request(transaction, unit, pdu)
        self._arm_frame_deadline()
        # Back-pressure: a client pipelining faster than it is answered, or not
        # reading its answers, is not read either.
        if self.blocked or len(buffer) > BACKLOG_BYTES or self.ended:
            transport.pause_reading()
        elif not self.waiting:
            transport.resume_reading()
        self._finish_if_ended()

    def _request(self, transaction: int, unit: int, pdu: bytes) -> None:
        self.requests += 1
        self.last_request = time.monotonic()  # (the idle watch reads it)
        try:
            answer = exception(pdu[0], ILLEGAL_FUNCTION) if self._refuses(unit, pdu[0]) \
                else self.server.handle(unit, pdu, self.writes, self.who)
        except Exception:  # a fault of ours must not cost the client its connection
            log.exception("Modbus TCP: a request from %s failed", self.peer)
            answer = exception(pdu[0], DEVICE_FAILURE)
        if isinstance(answer, bytes):
            self._send(transaction, unit, answer)
            return
        self.waiting = True
        task = asyncio.ensure_future(answer)
        task.add_done_callback(functools.partial(self._done, transaction=transaction,
                                                 unit=unit, function=pdu[0]))

    def _arm_frame_deadline(self) -> None:
        """A started frame must be whole in time; a complete one waiting its turn is
        not late (it waits for the answers before it, not for the client)."""
        started = bool(self.buffer) and not (self.waiting or self.blocked)
        if started and self.frame_timer is None:
            self.frame_timer = asyncio.get_running_loop().call_later(
                FRAME_DEADLINE_S, self._time_out, "frame_timeouts")
        elif not started and self.frame_timer is not None:
            self.frame_timer.cancel()
            self.frame_timer = None

    def _finish_if_ended(self) -> None:
        # Every whole request that came before the FIN is answered by now (or is
        # in progress, or waits for the client to read): what is left is a fragment.
        if self.ended and not (self.waiting or self.blocked) and self.transport is not None:
            self.transport.close()  # after the answers written so far

    def _done(self, task: asyncio.Future[bytes], transaction: int, unit: int,
              function: int) -> None:
        self.waiting = False
        if task.cancelled():
            return
        error = task.exception()
        if error is not None:
            log.error("Modbus TCP: request from %s failed: %r", self.peer, error)
            answer = exception(function, DEVICE_FAILURE)
        else:
            answer = task.result()
        self._send(transaction, unit, answer)
        if self.transport is not None and not self.transport.is_closing():
            self._answer_what_is_complete()

    def _send(self, transaction: int, unit: int, pdu: bytes) -> None:
        assert self.transport is not None
        if not self.transport.is_closing():
            self.transport.write(MBAP.pack(transaction, 0, len(pdu) + 1, unit) + pdu)
