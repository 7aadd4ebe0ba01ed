"""Modbus/TCP Security (docs/modbus-tcp.md, issue 28): mutual TLS and role-based rights,
from the side of the client trying to get in.

The gateway runs on a simulated Modbus-RTU sensor; the clients are pymodbus's TLS
client and plain TLS sockets, with certificates this test makes with ``cryptography``
(its own CA, and another one the gateway does not trust), and, in the last test, with
the very ``openssl`` commands docs/modbus-tcp.md gives.  One test runs the gateway as
its own process, its descriptors limited, against connections that never handshake.
Waits are deadlines on a condition, never measurements.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import errno
import ipaddress
import json
import logging
import os
import re
import resource
import select
import shutil
import socket
import ssl
import struct
import subprocess
import sys
import time
import urllib.request
import warnings
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID
from pymodbus.client import AsyncModbusTlsClient
from support import ROOT
from support.harness import free_port, interrupt, running, until

from imu_gateway.app import Gateway
from imu_gateway.config import config_from_dict
from imu_gateway.errors import ConfigError, StartupError
from imu_gateway.frontends.modbus import tls as modbus_tls
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

DOC = ROOT / "docs" / "modbus-tcp.md"
FAST = 115200
READING = Motion.from_seed(5).sample(3.0)
MBAP = struct.Struct(">HHHB")
ILLEGAL_FUNCTION = 0x01
# The spec's role extension, written out here so the test does not trust the server's.
ROLE_OID = x509.ObjectIdentifier("1.3.6.1.4.1.50316.802.1")
UNIT, RAW_UNIT = 1, 50  # the VG's map unit and its pass-through unit
ZERO_TYPE = 1000  # the map's zero-type command register (docs/register-map.md)


# ------------------------------------------------------------------ certificates


@dataclass(frozen=True)
class Pem:
    cert: Path
    key: Path


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _issue(folder: Path, name: str, issuer: tuple[x509.Name, ec.EllipticCurvePrivateKey] | None,
           extensions: list[tuple[x509.ExtensionType, bool]]) -> tuple[Pem, Any]:
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.UTC)
    issuer_name, issuer_key = issuer or (_name(name), key)
    builder = (x509.CertificateBuilder().subject_name(_name(name)).issuer_name(issuer_name)
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now - datetime.timedelta(minutes=5))
               .not_valid_after(now + datetime.timedelta(days=2)))
    for extension, critical in extensions:
        builder = builder.add_extension(extension, critical)
    cert = builder.sign(issuer_key, hashes.SHA256())
    pem = Pem(folder / f"{name}.crt", folder / f"{name}.key")
    pem.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    pem.key.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                          serialization.PrivateFormat.PKCS8,
                                          serialization.NoEncryption()))
    return pem, (cert.subject, key)


def _role(text: str, critical: bool = False,
          oid: x509.ObjectIdentifier = ROLE_OID) -> tuple[x509.ExtensionType, bool]:
    utf8 = text.encode()
    assert len(utf8) < 128  # the short form of the DER length
    return x509.UnrecognizedExtension(oid, bytes([0x0C, len(utf8)]) + utf8), critical


def _der(tag: int, body: bytes) -> bytes:
    """One DER TLV (the long form of the length for 128 bytes and more)."""
    size = len(body)
    if size < 128:
        return bytes((tag, size)) + body
    octets = size.to_bytes((size.bit_length() + 7) // 8, "big")
    return bytes((tag, 0x80 | len(octets))) + octets + body


def _two_roles(folder: Path, issuer: tuple[x509.Name, ec.EllipticCurvePrivateKey]) -> Pem:
    """A certificate with two Modbus Role extensions, Viewer and Engineer, signed by the
    CA.  ``cryptography`` builds no such thing, so the second role is built under a twin
    OID of the same length, renamed in the signed part, and that part signed again."""
    twin = x509.ObjectIdentifier("1.3.6.1.4.1.50316.802.9")
    pem, _ = _issue(folder, "two-roles", issuer, [LEAF, _role("Viewer"),
                                                   _role("Engineer", oid=twin)])
    cert = x509.load_pem_x509_certificate(pem.cert.read_bytes())
    tbs = cert.tbs_certificate_bytes
    assert tbs.count(_oid_der(twin)) == 1
    tbs = tbs.replace(_oid_der(twin), _oid_der(ROLE_OID))
    signature = issuer[1].sign(tbs, ec.ECDSA(hashes.SHA256()))
    algorithm = _der(0x30, _oid_der(cert.signature_algorithm_oid))  # (no parameters)
    der = _der(0x30, tbs + algorithm + _der(0x03, b"\0" + signature))
    twice = x509.load_der_x509_certificate(der)
    with pytest.raises(x509.DuplicateExtension):
        twice.extensions  # noqa: B018 (what the gateway meets)
    pem.cert.write_bytes(twice.public_bytes(serialization.Encoding.PEM))
    return pem


def _oid_der(oid: x509.ObjectIdentifier) -> bytes:
    """An OID in DER: base 128, the first two arcs in one."""
    arcs = [int(a) for a in oid.dotted_string.split(".")]
    body = bytearray([40 * arcs[0] + arcs[1]])
    for arc in arcs[2:]:
        digits = [arc & 0x7F]
        while arc > 0x7F:
            arc >>= 7
            digits.append(0x80 | (arc & 0x7F))
        body += bytes(reversed(digits))
    return _der(0x06, bytes(body))


CA_EXTENSION = (x509.BasicConstraints(ca=True, path_length=0), True)
LEAF = (x509.BasicConstraints(ca=False, path_length=None), True)


@dataclass(frozen=True)
class Pki:
    ca: Pem
    server: Pem
    # viewer, operator, engineer, no-role, janitor, rogue; critical (its role extension
    # marked so), two-roles (Viewer and Engineer)
    clients: dict[str, Pem]


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Pki:
    folder = tmp_path_factory.mktemp("pki")
    ca, ca_issuer = _issue(folder, "test-ca", None, [CA_EXTENSION])
    san = (x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
           False)
    server, _ = _issue(folder, "gateway", ca_issuer, [LEAF, san])
    clients = {name: _issue(folder, name, ca_issuer, [LEAF, *role])[0] for name, role in (
        ("viewer", [_role("Viewer")]), ("operator", [_role("Operator")]),
        ("engineer", [_role("Engineer")]), ("no-role", []), ("janitor", [_role("Janitor")]))}
    _, other_issuer = _issue(folder, "other-ca", None, [CA_EXTENSION])
    clients["rogue"], _ = _issue(folder, "rogue", other_issuer, [LEAF, _role("Engineer")])
    clients["critical"], _ = _issue(folder, "critical", ca_issuer,
                                    [LEAF, _role("Operator", critical=True)])
    clients["two-roles"] = _two_roles(folder, ca_issuer)
    return Pki(ca, server, clients)


def client_context(pki: Pki, client: str | None,
                   max_version: ssl.TLSVersion | None = None) -> ssl.SSLContext:
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.load_verify_locations(pki.ca.cert)
    if client is not None:
        pem = pki.clients[client]
        context.load_cert_chain(pem.cert, pem.key)
    if max_version is not None:
        context.maximum_version = max_version
    return context


# ------------------------------------------------------------------ the gateway


def tls_section(pki: Pki, **extra: Any) -> dict[str, Any]:
    return {"listen": "127.0.0.1:0", "certfile": str(pki.server.cert),
            "keyfile": str(pki.server.key), "ca_file": str(pki.ca.cert), **extra}


@contextlib.asynccontextmanager
async def gateway(tls: dict[str, Any], alarms: tuple[dict[str, Any], ...] = (),
                  **modbus: Any) -> AsyncIterator[Gateway]:
    """A Modbus-RTU VG on unit 1, its own registers on unit 50, holding a reading."""
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=FAST, source=hold(READING))
    with simulated([vg]) as line:
        config = {"gateway_id": "tls-test", "buses": [{
            "name": "line", "port": line.path, "baudrate": FAST, "protocol": "modbus",
            "timeout_ms": 300, "sensors": [{"name": "vg", "series": "VG", "address": 1,
                                            "unit_id": UNIT, "raw_unit_id": RAW_UNIT,
                                            "alarms": list(alarms)}]}],
            "modbus": {"listen": None, "tls": tls, **modbus}}
        async with running(config) as gw:
            await until(lambda: gw.cache.snapshot("vg").seq >= 1)
            yield gw


def tls_port(gw: Gateway) -> int:
    assert gw.modbus is not None
    return gw.modbus.tls_port


@contextlib.asynccontextmanager
async def pymodbus_tls(gw: Gateway, pki: Pki, client: str) -> AsyncIterator[AsyncModbusTlsClient]:
    modbus = AsyncModbusTlsClient("127.0.0.1", port=tls_port(gw), timeout=5, retries=0,
                                  sslctx=client_context(pki, client))
    assert await modbus.connect(), f"{client}: pymodbus could not connect"
    try:
        yield modbus
    finally:
        modbus.close()


async def answer_of(call: Any) -> int | None:
    """None for a normal answer, else its exception code."""
    rr = await call
    return rr.exception_code if rr.isError() else None


async def rights_seen(modbus: AsyncModbusTlsClient) -> dict[str, int | None]:
    """What the gateway answers this client: a read, a device identification, a write
    of the zero type (relative), and a read and a write of the sensor's own registers."""
    return {
        "read": await answer_of(modbus.read_holding_registers(0, count=9, device_id=UNIT)),
        "identify": await answer_of(modbus.read_device_information(device_id=UNIT)),
        "write": await answer_of(modbus.write_register(ZERO_TYPE, 1, device_id=UNIT)),
        "raw read": await answer_of(modbus.read_holding_registers(
            0x22, count=2, device_id=RAW_UNIT)),
        "raw write": await answer_of(modbus.write_register(0x0A, 0, device_id=RAW_UNIT)),
    }


REFUSED_ALL = dict.fromkeys(("read", "identify", "write", "raw read", "raw write"),
                            ILLEGAL_FUNCTION)
VIEWER = {"read": None, "identify": None, "write": ILLEGAL_FUNCTION,
          "raw read": ILLEGAL_FUNCTION, "raw write": ILLEGAL_FUNCTION}


def own_listening_ports() -> set[int]:
    """The TCP ports this process listens on (from /proc: what a port scan would find)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(OSError):
            link = os.readlink(f"/proc/self/fd/{fd}")
            if link.startswith("socket:["):
                inodes.add(link[8:-1])
    ports = set()
    for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


# ------------------------------------------------------------------ rights by role


@pytest.mark.anyio
async def test_each_role_gets_its_rights_and_the_plain_port_is_off(pki: Pki) -> None:
    before = own_listening_ports()
    async with gateway(tls_section(pki)) as gw:
        # listen: null: the TLS port is the only one the gateway opened
        assert own_listening_ports() - before == {tls_port(gw)}
        async with pymodbus_tls(gw, pki, "viewer") as viewer:
            assert await rights_seen(viewer) == VIEWER
            assert gw.cache.settings("vg").zero_type != "relative"
        async with pymodbus_tls(gw, pki, "operator") as operator:
            assert await rights_seen(operator) == {**VIEWER, "write": None}
            assert gw.cache.settings("vg").zero_type == "relative"  # it reached the sensor
        async with pymodbus_tls(gw, pki, "engineer") as engineer:
            seen = await rights_seen(engineer)
            assert seen == {**VIEWER, "write": None, "raw read": None, "raw write": None}
            assert gw.cache.settings("vg").zero_type == "absolute"  # through its own register
        assert gw.modbus is not None and gw.modbus.stats()["refused_role"] == 5


@pytest.mark.anyio
async def test_allow_writes_is_the_plain_ports_and_the_role_decides_on_tls(pki: Pki) -> None:
    """allow_writes: true opens the plain port to writes, not a Viewer's TLS connection;
    allow_writes: false does not close it to an Operator."""
    for allow_writes in (True, False):
        async with gateway(tls_section(pki), allow_writes=allow_writes) as gw:
            async with pymodbus_tls(gw, pki, "viewer") as viewer:
                assert await answer_of(viewer.write_register(ZERO_TYPE, 1, device_id=UNIT)) \
                    == ILLEGAL_FUNCTION
            async with pymodbus_tls(gw, pki, "operator") as operator:
                assert await answer_of(operator.write_register(
                    ZERO_TYPE, 1, device_id=UNIT)) is None


@pytest.mark.anyio
async def test_a_viewer_reads_the_alarms_bits_and_only_a_writer_acknowledges(pki: Pki) -> None:
    """Alarms (docs/register-map.md): FC 01 and 02 need ``read``, FC 05 (acknowledge)
    ``write``; a Viewer sees the alarm and its acknowledgement is refused with 01,
    whatever allow_writes says; an Operator's is journalled under its certificate."""
    beyond = {"name": "always", "field": "pitch", "above": -89.0}  # active at once
    async with gateway(tls_section(pki), alarms=(beyond,), allow_writes=True) as gw:
        async with pymodbus_tls(gw, pki, "viewer") as viewer:
            async def bits() -> tuple[list[bool], list[bool]]:
                inputs = await viewer.read_discrete_inputs(0, count=2, device_id=UNIT)
                coils = await viewer.read_coils(0, count=2, device_id=UNIT)
                assert not inputs.isError() and not coils.isError(), (inputs, coils)
                return list(inputs.bits[:2]), list(coils.bits[:2])

            async def raised() -> bool:
                return await bits() == ([True, False], [True, False])
            await until(raised)  # "always", then communication: active, unacknowledged
            assert await answer_of(viewer.write_coil(0, True, device_id=UNIT)) == \
                ILLEGAL_FUNCTION
            assert await bits() == ([True, False], [True, False])
        assert [t.to_state.value for t in gw.alarm_journal()] == ["active_unacked"]
        assert gw.modbus is not None and gw.modbus.stats()["refused_role"] == 1
        async with pymodbus_tls(gw, pki, "operator") as operator:
            assert await answer_of(operator.write_coil(0, True, device_id=UNIT)) is None
            coils = await operator.read_coils(0, count=2, device_id=UNIT)
            assert list(coils.bits[:2]) == [False, False]
        acked = gw.alarm_journal()[-1]
        assert (acked.to_state.value, acked.by) == ("active_acked",
                                                    "CN=operator (modbus 127.0.0.1)")


@pytest.mark.anyio
async def test_no_role_or_an_unknown_one_is_refused_everything_logged_once(
        pki: Pki, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, "imu_gateway.modbus")
    async with gateway(tls_section(pki)) as gw:
        for client in ("no-role", "janitor"):
            async with pymodbus_tls(gw, pki, client) as modbus:
                assert await rights_seen(modbus) == REFUSED_ALL, client
                # a unit that does not exist is refused the same: nothing is learnt
                assert await answer_of(modbus.read_holding_registers(
                    0, count=1, device_id=77)) == ILLEGAL_FUNCTION
    refusals = [r.getMessage() for r in caplog.records if "refused FC" in r.getMessage()]
    assert len(refusals) == 1, refusals  # the first of a connection; the rest are counted
    assert "CN=no-role" in refusals[0] and "exception 01" in refusals[0]
    roles = [r.getMessage() for r in caplog.records if "default_role" in r.getMessage()]
    assert roles and "no role extension" in roles[0], roles


@pytest.mark.anyio
async def test_default_role_gives_its_rights_to_the_roleless(pki: Pki) -> None:
    async with gateway(tls_section(pki, default_role="Viewer")) as gw:
        for client in ("no-role", "janitor"):
            async with pymodbus_tls(gw, pki, client) as modbus:
                assert await rights_seen(modbus) == VIEWER, client


@pytest.mark.anyio
async def test_two_role_extensions_get_no_rights_not_even_the_default(
        pki: Pki, caplog: pytest.LogCaptureFixture) -> None:
    """A certificate with two roles (Viewer and Engineer): which was meant is not known,
    so it gets nothing, not default_role's rights either; one warning says why, and
    no traceback (it was asyncio's ERROR for every such connection)."""
    caplog.set_level(logging.WARNING)
    async with gateway(tls_section(pki, default_role="Engineer")) as gw:
        for _ in range(3):
            async with pymodbus_tls(gw, pki, "two-roles") as modbus:
                assert await rights_seen(modbus) == REFUSED_ALL
        async with pymodbus_tls(gw, pki, "viewer") as viewer:  # the others are as they were
            assert await rights_seen(viewer) == VIEWER
    said = [r.getMessage() for r in caplog.records if "ambiguous" in r.getMessage()]
    assert len(said) == 1, said  # rate-limited: one line for the three connections
    assert "CN=two-roles" in said[0] and "no rights, whatever default_role" in said[0]
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


@pytest.mark.anyio
async def test_roles_are_the_configs(pki: Pki) -> None:
    """A role map of the config's own: Viewer may write here, Operator is not a role."""
    roles = {"Viewer": ["read", "write"], "Engineer": ["passthrough"]}
    async with gateway(tls_section(pki, roles=roles)) as gw:
        async with pymodbus_tls(gw, pki, "viewer") as viewer:
            assert await rights_seen(viewer) == {**VIEWER, "write": None}
        async with pymodbus_tls(gw, pki, "operator") as operator:
            assert await rights_seen(operator) == REFUSED_ALL
        async with pymodbus_tls(gw, pki, "engineer") as engineer:
            assert await rights_seen(engineer) == {
                **REFUSED_ALL, "raw read": None, "raw write": None}


# ------------------------------------------------------------------ the handshake


class TlsRaw:
    """A Modbus client on a TLS stream: every byte after the handshake is the test's."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def connect(cls, port: int, context: ssl.SSLContext) -> TlsRaw:
        reader, writer = await asyncio.wait_for(asyncio.open_connection(
            "127.0.0.1", port, ssl=context), 10)
        return cls(reader, writer)

    async def send(self, data: bytes) -> None:
        self.writer.write(data)
        await self.writer.drain()

    async def receive(self) -> tuple[int, int, bytes]:
        """One answer: transaction id, unit id, PDU."""
        header = await asyncio.wait_for(self.reader.readexactly(MBAP.size), 10)
        tid, _, length, unit = MBAP.unpack(header)
        return tid, unit, await asyncio.wait_for(self.reader.readexactly(length - 1), 10)

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError, ssl.SSLError):
            await self.writer.wait_closed()


def request(tid: int, unit: int, pdu: bytes) -> bytes:
    return MBAP.pack(tid, 0, len(pdu) + 1, unit) + pdu


STATUS_READ = struct.pack(">BHH", 3, 0, 9)


async def refused(port: int, context: ssl.SSLContext) -> None:
    """The gateway refuses this client: the handshake, or the first read after it,
    fails (TLS 1.3 verifies a client's certificate after the client's side has
    finished); a request is never answered."""
    try:
        raw = await TlsRaw.connect(port, context)
    except (ssl.SSLError, ConnectionError):
        return
    try:
        await raw.send(request(1, UNIT, STATUS_READ))
        assert await asyncio.wait_for(raw.reader.read(100), 10) == b""
    except (ssl.SSLError, ConnectionError):
        pass
    finally:
        await raw.close()


@pytest.mark.anyio
async def test_untrusted_missing_and_old_clients_are_refused_at_the_handshake(
        pki: Pki, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, "imu_gateway.modbus")

    def logged() -> str:
        return "\n".join(r.getMessage() for r in caplog.records
                         if "at the TLS handshake" in r.getMessage())

    async with gateway(tls_section(pki, default_role="Engineer")) as gw:
        port = tls_port(gw)
        assert gw.modbus is not None
        gw.modbus.peers.period = 0  # every refusal logged, to see each one's reason
        # another CA's certificate, though its role would be Engineer
        await refused(port, client_context(pki, "rogue"))
        await until(lambda: "unable to get local issuer certificate" in logged())
        # no certificate at all, on TLS 1.3 and on TLS 1.2
        for version in (None, ssl.TLSVersion.TLSv1_2):
            caplog.clear()
            await refused(port, client_context(pki, None, version))
            await until(lambda: "it sent no client certificate" in logged())
        # a client that speaks TLS 1.1 at most: no common version
        with warnings.catch_warnings():  # (old on purpose)
            warnings.simplefilter("ignore", DeprecationWarning)
            old = client_context(pki, "operator", ssl.TLSVersion.TLSv1_1)
            old.minimum_version = ssl.TLSVersion.TLSv1
        old.set_ciphers("DEFAULT:@SECLEVEL=0")  # (so that the refusal is the gateway's)
        await refused(port, old)
        await until(lambda: "TLS 1.2 or later is required" in logged())
        # a role extension marked critical: OpenSSL refuses the certificate itself
        caplog.clear()
        await refused(port, client_context(pki, "critical"))
        await until(lambda: "must not be critical" in logged())
        assert "1.3.6.1.4.1.50316.802.1" in logged() and "signed by the CA" not in logged()
        assert gw.modbus.stats()["refused_handshake"] == 5
        # and none of them cost a well-behaved client its service, on TLS 1.2 either
        for version in (None, ssl.TLSVersion.TLSv1_2):
            raw = await TlsRaw.connect(port, client_context(pki, "viewer", version))
            try:
                await raw.send(request(7, UNIT, STATUS_READ))
                tid, unit, pdu = await raw.receive()
                assert (tid, unit, pdu[:2]) == (7, UNIT, bytes((3, 18)))
            finally:
                await raw.close()


@pytest.mark.anyio
async def test_a_client_that_never_handshakes_gives_way_and_is_closed_in_time(
        pki: Pki, monkeypatch: pytest.MonkeyPatch) -> None:
    """Connections that never handshake hold places of max_connections, the first
    given up to a newcomer: a real client is served at once, and the rest are closed
    by the handshake deadline."""
    monkeypatch.setattr(modbus_tls, "HANDSHAKE_TIMEOUT_S", 1.0)
    async with gateway(tls_section(pki), max_connections=2) as gw:
        assert gw.modbus is not None
        port = tls_port(gw)
        silent = [await asyncio.open_connection("127.0.0.1", port) for _ in range(4)]
        await until(lambda: gw.modbus is not None and gw.modbus.stats()["connections"] == 4)
        assert gw.modbus.stats()["handshaking"] == 2  # the newest two: the others gave way
        async with pymodbus_tls(gw, pki, "viewer") as viewer:
            assert await answer_of(viewer.read_holding_registers(
                0, count=9, device_id=UNIT)) is None
            for reader, writer in silent:
                assert await asyncio.wait_for(reader.read(100), 10) == b""
                writer.close()
            stats = gw.modbus.stats()
            assert (stats["clients"], stats["handshaking"]) == (1, 0)
        assert stats["evicted_limit"] == 3  # two for the 3rd and 4th, one for the viewer
        assert stats["handshake_timeouts"] == 1


def client_hello(context: ssl.SSLContext) -> bytes:
    """The first flight of a TLS client on ``context``."""
    incoming, outgoing = ssl.MemoryBIO(), ssl.MemoryBIO()
    tls = context.wrap_bio(incoming, outgoing, server_hostname="127.0.0.1")
    with contextlib.suppress(ssl.SSLWantReadError):
        tls.do_handshake()
    return outgoing.read()


@pytest.mark.anyio
async def test_allow_from_closes_a_stranger_before_its_handshake(pki: Pki) -> None:
    """A client from an address outside allow_from is closed before the handshake: it
    gets not one byte of TLS (no ServerHello, no certificate), however good its own
    (before: the handshake was done, and the client closed after it); one from inside
    is served."""
    async with gateway(tls_section(pki), allow_from=["127.0.0.2/32"]) as gw:
        assert gw.modbus is not None
        context = client_context(pki, "engineer")
        reader, writer = await asyncio.open_connection("127.0.0.1", tls_port(gw))
        writer.write(client_hello(context))
        try:
            first = await asyncio.wait_for(reader.read(1), 10)
        except ConnectionError:
            first = b""
        writer.close()
        assert first == b"", "the gateway began a TLS handshake with a stranger"
        reader, writer = await asyncio.wait_for(asyncio.open_connection(
            "127.0.0.1", tls_port(gw), ssl=context, local_addr=("127.0.0.2", 0)), 10)
        inside = TlsRaw(reader, writer)
        try:
            await inside.send(request(3, UNIT, STATUS_READ))
            assert (await inside.receive())[2][:2] == bytes((3, 18))
        finally:
            await inside.close()
        stats = gw.modbus.stats()
        assert (stats["refused_address"], stats.get("refused_handshake", 0)) == (1, 0)


@pytest.mark.anyio
async def test_pipelined_requests_on_tls_are_each_answered_in_order(pki: Pki) -> None:
    async with gateway(tls_section(pki)) as gw:
        raw = await TlsRaw.connect(tls_port(gw), client_context(pki, "viewer"))
        try:
            # a read, a refused write and a read in one TLS record
            write = struct.pack(">BHH", 6, ZERO_TYPE, 1)
            await raw.send(request(1, UNIT, STATUS_READ) + request(2, UNIT, write)
                           + request(3, UNIT, struct.pack(">BHH", 4, 0, 2)))
            answers = [await raw.receive() for _ in range(3)]
            assert [(tid, unit) for tid, unit, _ in answers] == [(1, UNIT), (2, UNIT),
                                                                 (3, UNIT)]
            assert answers[0][2][:2] == bytes((3, 18))
            assert answers[1][2] == bytes((0x86, ILLEGAL_FUNCTION))
            assert answers[2][2][:2] == bytes((4, 4))
        finally:
            await raw.close()


# ------------------------------------------------------------------ descriptors

NOFILE = 256  # the gateway process's descriptor limit in the next test
ATTACKERS = [f"127.0.0.{n}" for n in range(2, 10)]  # eight addresses, loopback only
HELD = 40  # connections each opens and holds, never sending a byte: 320 in all
PROMPT_S = 5.0  # a real client's connect, handshake and read, each; it needs milliseconds


class TlsProcess:
    """``python -m imu_gateway run`` with the TLS port alone (its counts over HTTP),
    limited to ``NOFILE`` descriptors the way a service's soft limit would."""

    def __init__(self, process: subprocess.Popen[bytes], port: int, http: int,
                 log: Path) -> None:
        self.process, self.port, self.http, self.log = process, port, http, log

    def fds(self) -> int:
        return len(os.listdir(f"/proc/{self.process.pid}/fd"))

    def counts(self) -> dict[str, Any] | None:
        """``frontends.modbus`` of /api/v1/health; None while it does not answer."""
        url = f"http://127.0.0.1:{self.http}/api/v1/health"
        try:
            with urllib.request.urlopen(url, timeout=PROMPT_S) as answer:
                modbus: dict[str, Any] = json.load(answer)["frontends"]["modbus"]
                return modbus
        except OSError:
            return None

    def until(self, condition: Callable[[], bool], what: str, timeout: float = 30) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert self.process.poll() is None, self.log.read_text()[-3000:]
            assert time.monotonic() < deadline, (
                f"{what}, not within {timeout} s: {self.unaccepted()} connections wait to "
                f"be accepted, the gateway has {self.fds()} descriptors")
            time.sleep(0.02)

    def unaccepted(self) -> int:
        """Connections the kernel completed that the gateway has not accepted: the
        accept queue of its listening socket (/proc/net/tcp)."""
        for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == self.port:
                return int(fields[4].split(":")[1], 16)
        raise AssertionError(f"nothing listens on port {self.port}")


@contextlib.contextmanager
def tls_process(tmp_path: Path, pki: Pki, **modbus: Any) -> Iterator[TlsProcess]:
    vg = make_sensor(WireProtocol.MODBUS, Series.VG, 1, baud=FAST, source=hold(READING))
    with simulated([vg]) as line:
        port, http = free_port(), free_port()
        config = {"gateway_id": "tls-fds", "buses": [{
            "name": "line", "port": line.path, "baudrate": FAST, "protocol": "modbus",
            "sensors": [{"name": "vg", "series": "VG", "address": 1, "unit_id": UNIT}]}],
            "modbus": {"listen": None, "tls": tls_section(pki, listen=f"127.0.0.1:{port}"),
                       **modbus},
            "http": {"listen": f"127.0.0.1:{http}"}}
        path, log = tmp_path / "gateway.yaml", tmp_path / "gateway.log"
        path.write_text(yaml.safe_dump(config))
        with log.open("wb") as out:
            process = subprocess.Popen(
                [sys.executable, "-m", "imu_gateway", "run", "-c", str(path)],
                stdout=out, stderr=subprocess.STDOUT)
        try:
            # (before it listens: the interpreter is still starting)
            resource.prlimit(process.pid, resource.RLIMIT_NOFILE, (NOFILE, NOFILE))
            gw = TlsProcess(process, port, http, log)
            gw.until(lambda: gw.counts() is not None, "the gateway's API answers")
            yield gw
        finally:
            interrupt(process)
    text = log.read_text()
    assert process.returncode == 0 and "Traceback" not in text, text[-3000:]
    assert "Too many open files" not in text and "out of system resource" not in text
    assert "WARNING asyncio" not in text, text[-3000:]  # (one for each TLS client's close)


class RealClient:
    """A client with a good certificate on a blocking TLS socket, each step within
    ``PROMPT_S``: what a SCADA poller does."""

    def __init__(self, port: int, context: ssl.SSLContext) -> None:
        sock = socket.create_connection(("127.0.0.1", port), timeout=PROMPT_S)
        self.tls = context.wrap_socket(sock, server_hostname="127.0.0.1")

    def read_status(self) -> None:
        self.tls.sendall(request(5, UNIT, STATUS_READ))
        answer = b""
        while len(answer) < MBAP.size + 2 + 18:
            chunk = self.tls.recv(4096)
            assert chunk, "the gateway closed a real client's connection"
            answer += chunk
        assert answer[MBAP.size - 1:MBAP.size + 2] == bytes((UNIT, 3, 18)), answer

    def close(self) -> None:
        self.tls.close()


def hold_silent(host: str, port: int, count: int) -> list[socket.socket]:
    """``count`` TCP connections from ``host`` that will never send a byte, once the
    kernel has made each (the gateway need not have accepted them)."""
    socks = []
    for _ in range(count):
        sock = socket.socket()
        socks.append(sock)
        sock.setblocking(False)
        sock.bind((host, 0))
        assert sock.connect_ex(("127.0.0.1", port)) in (0, errno.EINPROGRESS)
    for sock in socks:
        assert select.select([], [sock], [], PROMPT_S)[1], "a connect did not complete"
        assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == 0
    return socks


def test_connections_that_never_handshake_cannot_take_the_gateways_descriptors(
        tmp_path: Path, pki: Pki) -> None:
    """Eight addresses open 40 TCP connections each to the TLS port and send nothing:
    320, more than the gateway's 256 descriptors.  Before, each held a descriptor until
    its handshake deadline (accept then failed with EMFILE: every port, every file).
    Now they count against the limits like any connection (20, and 10 an address), the
    unfinished handshake giving way first: the descriptors stay bounded, and a real
    client, connected before or new, is served at once after every wave."""
    limit, per_address = 20, 10
    context = client_context(pki, "viewer")
    with tls_process(tmp_path, pki, max_connections=limit,
                     max_connections_per_address=per_address) as gw:
        polling = RealClient(gw.port, context)
        polling.read_status()
        before = gw.fds()  # the process's own, the listening sockets and this client
        bound = before + limit + 8  # (8: the health request's, and one closing)
        held: list[socket.socket] = []
        try:
            for wave, host in enumerate(ATTACKERS, 1):
                held += hold_silent(host, gw.port, HELD)
                gw.until(lambda: gw.unaccepted() == 0, f"wave {wave}: all accepted")
                # well within the handshake deadline: it is the limits that close them
                gw.until(lambda: gw.fds() <= bound, f"wave {wave}: {bound} descriptors "
                         "or fewer", timeout=2.0)
                polling.read_status()  # the client that was connected is still served
                fresh = RealClient(gw.port, context)  # and a new one gets in
                try:
                    fresh.read_status()
                finally:
                    fresh.close()
        finally:
            for sock in held:
                sock.close()
            polling.close()
        counts = gw.counts()
        assert counts is not None
        assert counts["connections"] == 1 + len(held) + len(ATTACKERS), counts
        assert counts["evicted_per_address"] == len(ATTACKERS) * (HELD - per_address)
        assert counts["evicted_limit"] > 0 and counts["handshaking"] <= limit, counts


# ------------------------------------------------------------------ config and startup


def base_config(modbus: dict[str, Any]) -> dict[str, Any]:
    return {"buses": [{"name": "b", "port": "loop://", "protocol": "native",
                       "sensors": [{"name": "s", "series": "AH"}]}], "modbus": modbus}


def problems_of(modbus: dict[str, Any]) -> str:
    with pytest.raises(ConfigError) as caught:
        config_from_dict(base_config(modbus), env={})
    return str(caught.value)


def test_config_names_what_is_wrong(pki: Pki) -> None:
    assert "modbus: listen: null turns the plain port off, and there is no tls" in \
        problems_of({"listen": None})
    assert 'default_role: "Admin" is not in roles (Viewer, Operator, Engineer)' in \
        problems_of({"tls": tls_section(pki, default_role="Admin")})
    assert "modbus.tls.roles.Viewer[0]: input should be 'read', 'write' or 'passthrough'" \
        in problems_of(
        {"tls": tls_section(pki, roles={"Viewer": ["admin"]})})
    assert "modbus.tls.ca_file: no such file" in problems_of(
        {"tls": tls_section(pki, ca_file="/nonexistent/ca.pem")})
    config = config_from_dict(base_config({"tls": tls_section(pki, listen="0.0.0.0:802")}),
                              env={})
    assert config.modbus is not None and config.modbus.tls is not None
    assert str(config.modbus.listen) == "0.0.0.0:502"  # the plain port stays as it was
    assert config.modbus.tls.default_role is None
    assert config.modbus.tls.roles == {"Viewer": ["read"], "Operator": ["read", "write"],
                                       "Engineer": ["read", "write", "passthrough"]}


@pytest.mark.anyio
async def test_an_unusable_certificate_stops_the_start_naming_the_file(pki: Pki) -> None:
    bad = pki.server.cert.parent / "not-a-key.pem"
    bad.write_text("-----BEGIN PRIVATE KEY-----\nnonsense\n-----END PRIVATE KEY-----\n")
    with pytest.raises(StartupError, match=r"modbus\.tls\.certfile .*not-a-key\.pem"):
        async with gateway(tls_section(pki, keyfile=str(bad)), listen="127.0.0.1:0"):
            pass


# ------------------------------------------------------------------ the docs' openssl


def doc_block(heading: str) -> str:
    """The first ``sh`` block after a heading of docs/modbus-tcp.md."""
    text = DOC.read_text()
    at = text.index(heading)
    match = re.search(r"```sh\n(.*?)```", text[at:], re.DOTALL)
    assert match, f"no sh block after {heading!r}"
    return match.group(1)


@pytest.mark.anyio
async def test_the_docs_openssl_commands_make_certificates_the_gateway_accepts(
        tmp_path: Path) -> None:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    script = doc_block("### Certificates with openssl")
    done = await asyncio.to_thread(subprocess.run, ["bash", "-euo", "pipefail", "-c", script],
                                   cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    files = {name: tmp_path / name for name in (
        "ca.crt", "gateway.crt", "gateway.key", "operator.crt", "operator.key")}
    assert all(path.is_file() for path in files.values()), sorted(os.listdir(tmp_path))
    pki = Pki(Pem(files["ca.crt"], tmp_path / "ca.key"),
              Pem(files["gateway.crt"], files["gateway.key"]),
              {"operator": Pem(files["operator.crt"], files["operator.key"])})
    async with gateway(tls_section(pki)) as gw:
        async with pymodbus_tls(gw, pki, "operator") as client:
            # Operator: its role read from the openssl-made extension
            assert await rights_seen(client) == {**VIEWER, "write": None}
        # a PLC that has only the specification's TLS 1.2 suite is served too
        context = client_context(pki, "operator", ssl.TLSVersion.TLSv1_2)
        context.set_ciphers("AES128-SHA256")
        raw = await TlsRaw.connect(tls_port(gw), context)
        try:
            ssl_object = raw.writer.get_extra_info("ssl_object")
            assert ssl_object.cipher()[0] == "AES128-SHA256"
            await raw.send(request(9, UNIT, STATUS_READ))
            assert (await raw.receive())[2][:2] == bytes((3, 18))
        finally:
            await raw.close()
