"""The OPC UA server's doors, tried from the side of a client that skips its library's
endpoint checks (docs/opcua.md, "Security").  Each session here is built by hand on
asyncua's low-level client (``connect_socket``, ``send_hello``,
``open_secure_channel``, then ``uaclient.create_session`` / ``activate_session``), so
the server alone decides what gets through: OPC UA Part 4's SecureChannel and Session
services, and Part 2's rule that an endpoint's security is the least a client gets.
"""

from __future__ import annotations

import ipaddress
import logging
import shutil
import socket
import subprocess
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from asyncua.crypto import uacrypto
from asyncua.crypto.cert_gen import (
    generate_self_signed_app_certificate,
    setup_self_signed_certificate,
)
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256, encrypt_asymmetric
from asyncua.ua.uaerrors import UaStatusCodeError
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.x509.oid import ExtendedKeyUsageOID
from support.harness import free_port, running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "ua-door"
PASSWORD = "s3cret-door"
B256 = SecurityPolicyBasic256Sha256
Mode = ua.MessageSecurityMode


class Rig:
    def __init__(self, ah: SimSensor, path: str, tmp: Path) -> None:
        self.ah, self.path, self.tmp = ah, path, tmp
        self.pki = tmp / "pki"
        self.cert, self.key = tmp / "client" / "scada.der", tmp / "client" / "scada.pem"

    def config(self, port: int, **opcua: Any) -> dict[str, Any]:
        sensor = {"name": "boom", "series": "AH", "poll_hz": 10}
        return {"gateway_id": GID,
                "buses": [{"name": "a", "port": self.path, "baudrate": 115200,
                           "protocol": "native", "timeout_ms": 300, "sensors": [sensor]}],
                "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": str(self.pki), **opcua}}


@asynccontextmanager
async def made_rig(tmp_path: Path) -> AsyncIterator[Rig]:
    """A simulated AH on a line, and a client certificate the server trusts."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200,
                     source=hold(Motion.from_seed(3).sample(1.0)))
    with simulated([ah]) as line:
        r = Rig(ah, line.path, tmp_path)
        r.cert.parent.mkdir(parents=True)
        await setup_self_signed_certificate(
            r.key, r.cert, "urn:test:scada", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
            {"commonName": "scada"})
        (r.pki / "trusted").mkdir(parents=True)
        (r.pki / "trusted" / "scada.der").write_bytes(r.cert.read_bytes())
        yield r


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with made_rig(tmp_path) as r:
        yield r


# ------------------------------------------------------------------ a hand-built client

@asynccontextmanager
async def channel(rig: Rig, port: int, mode: ua.MessageSecurityMode = Mode.None_
                  ) -> AsyncIterator[Client]:
    """A secure channel and nothing more: no GetEndpoints, no check of what the server
    offers.  ``Mode.None_`` is a channel with no security at all."""
    client = Client(f"opc.tcp://127.0.0.1:{port}/", timeout=10)
    if mode is not Mode.None_:
        await client.set_security(B256, str(rig.cert), str(rig.key), mode=mode,
                                  server_certificate=str(rig.pki / "server_cert.der"))
    client.application_uri = "urn:test:scada"
    await client.connect_socket()
    try:
        await client.send_hello()
        await client.open_secure_channel()
        yield client
    finally:
        client.disconnect_socket()


async def create_session(client: Client) -> ua.CreateSessionResult:
    params = ua.CreateSessionParameters()
    params.ClientDescription = ua.ApplicationDescription(
        ApplicationUri="urn:test:scada", ApplicationType=ua.ApplicationType.Client)
    params.ClientNonce = b"n" * 32
    params.ClientCertificate = client.security_policy.host_certificate
    params.EndpointUrl = client.server_url.geturl()
    params.SessionName = "door"
    params.RequestedSessionTimeout = 60000
    result = await client.uaclient.create_session(params)
    client._server_nonce = result.ServerNonce
    return result


def _signature(client: Client) -> ua.SignatureData:
    """The client's proof of its certificate: the server's certificate and nonce,
    signed (empty on a channel with no security)."""
    challenge = (client.security_policy.peer_certificate or b"") + \
        (client._server_nonce or b"")
    return ua.SignatureData(
        Algorithm=client.security_policy.AsymmetricSignatureURI or B256.AsymmetricSignatureURI,
        Signature=client.security_policy.asymmetric_cryptography.signature(challenge))


async def activate(client: Client, token: ua.UserIdentityToken | None = None
                   ) -> ua.ActivateSessionResult:
    params = ua.ActivateSessionParameters()
    params.ClientSignature = _signature(client)
    params.UserIdentityToken = token or ua.AnonymousIdentityToken(PolicyId="anonymous")
    return await client.uaclient.activate_session(params)


def clear_password(user: str = "operator", password: str = PASSWORD) -> ua.UserNameIdentityToken:
    """A password in clear: ``EncryptionAlgorithm`` empty."""
    return ua.UserNameIdentityToken(PolicyId="username", UserName=user,
                                    Password=password.encode(), EncryptionAlgorithm=None)


def encrypted_password(rig: Rig, nonce: bytes, user: str = "operator") -> ua.UserNameIdentityToken:
    """A password encrypted for the server's certificate, as Part 4 7.41.2.3 asks."""
    server = uacrypto.x509_from_der((rig.pki / "server_cert.der").read_bytes())
    secret = ua.ua_binary.Primitives.Bytes.pack(PASSWORD.encode() + nonce)
    data, uri = encrypt_asymmetric(server.public_key(), secret, B256.URI)
    return ua.UserNameIdentityToken(PolicyId="username", UserName=user, Password=data,
                                    EncryptionAlgorithm=uri)


async def read(client: Client, nodeid: ua.NodeId) -> ua.DataValue:
    params = ua.ReadParameters()
    params.NodesToRead = [ua.ReadValueId(NodeId=nodeid, AttributeId=ua.AttributeIds.Value)]
    (value,) = await client.uaclient.read(params)
    return value


async def read_status(client: Client, ns: int = 2) -> ua.DataValue:
    """The sensor's Status (``ns``: the gateway's namespace index, when known)."""
    return await read(client, ua.NodeId(f"{GID}.Sensors.boom.Status", ns))


async def namespace(client: Client) -> int:
    names = await read(client, ua.NodeId(ua.ObjectIds.Server_NamespaceArray))
    return list(names.Value.Value).index("urn:imu-gateway")


async def call_declination(client: Client, ns: int = 2) -> ua.CallMethodResult:
    request = ua.CallMethodRequest(
        ObjectId=ua.NodeId(f"{GID}.Sensors.boom", ns),
        MethodId=ua.NodeId(f"{GID}.Sensors.boom.set_declination", ns),
        InputArguments=[ua.Variant(7.5, ua.VariantType.Double)])
    (result,) = await client.uaclient.call([request])
    return result


def refused(exc: pytest.ExceptionInfo[UaStatusCodeError], *codes: int) -> bool:
    return exc.value.code in codes


REJECTED = (ua.StatusCodes.BadSecurityModeRejected, ua.StatusCodes.BadSecurityPolicyRejected)


# ------------------------------------------------------------------ the tests

async def nothing_served(client: Client) -> None:
    """On a channel with no security, when None is off: no activation (anonymous or
    with a password in clear), no read, no call."""
    attempts: list[tuple[str, Any]] = [
        ("anonymous activation", lambda: activate(client)),
        ("activation with a clear password", lambda: activate(client, clear_password())),
        ("read", lambda: read_status(client)),
        ("call", lambda: call_declination(client))]
    for what, attempt in attempts:
        with pytest.raises(UaStatusCodeError) as refusal:
            await attempt()
        assert refused(refusal, *REJECTED), what


@pytest.mark.anyio
async def test_a_none_channel_serves_discovery_only_when_none_is_off(rig: Rig) -> None:
    """``allow_none: false``: a channel with no security still answers GetEndpoints and
    FindServers (a client needs them to choose a secured endpoint), and refuses every
    other service with BadSecurityModeRejected: no session (anonymous or with a
    password in clear), no read, no call; the sensor hears nothing."""
    port = free_port()
    cfg = rig.config(port, anonymous=False, allow_commands=True,
                     users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port) as client:
            endpoints = await client.uaclient.get_endpoints(ua.GetEndpointsParameters(
                EndpointUrl=client.server_url.geturl()))
            assert {e.SecurityMode for e in endpoints} == {Mode.Sign, Mode.SignAndEncrypt}
            servers = await client.uaclient.find_servers(ua.FindServersParameters())
            assert servers[0].ApplicationUri == f"urn:imu-gateway:{GID}"
            with pytest.raises(UaStatusCodeError) as no_session:
                await create_session(client)
            assert refused(no_session, *REJECTED)
            await nothing_served(client)
    assert rig.ah.settings.declination == 0.0
    assert not rig.ah.writes_heard


@pytest.mark.anyio
async def test_a_session_made_secure_cannot_be_taken_to_a_none_channel(rig: Rig) -> None:
    """Part 4 5.6.3: ActivateSession may move a session to a new channel.  A session
    created and activated on a signed channel, then activated again from a channel
    with no security (its authentication token is all it takes), is refused there;
    so are a read and a call that name it."""
    port = free_port()
    cfg = rig.config(port, anonymous=False, allow_commands=True,
                     users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.SignAndEncrypt) as secure:
            made = await create_session(secure)
            await activate(secure, encrypted_password(rig, made.ServerNonce))
            assert (await read_status(secure, await namespace(secure))).Value.Value == "ok"
            async with channel(rig, port) as plain:
                plain.uaclient.protocol.authentication_token = made.AuthenticationToken
                plain._server_nonce = made.ServerNonce
                await nothing_served(plain)
    assert rig.ah.settings.declination == 0.0
    assert not rig.ah.writes_heard


@pytest.mark.anyio
async def test_a_session_cannot_be_taken_by_another_client_certificate(rig: Rig) -> None:
    """Part 4 5.6.3.1: a session moves only to a channel of the certificate that
    created it.  A second trusted client that learnt the authentication token (and
    even the user's password) is refused BadSecurityChecksFailed; the first can move
    it to a new channel of its own."""
    port = free_port()
    other, other_key = rig.tmp / "client" / "other.der", rig.tmp / "client" / "other.pem"
    await setup_self_signed_certificate(
        other_key, other, "urn:test:scada", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": "other"})
    (rig.pki / "trusted" / "other.der").write_bytes(other.read_bytes())
    cfg = rig.config(port, anonymous=False, users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.SignAndEncrypt) as first:
            made = await create_session(first)
            done = await activate(first, encrypted_password(rig, made.ServerNonce))
            rig.cert, rig.key = other, other_key
            async with channel(rig, port, Mode.SignAndEncrypt) as thief:
                thief.uaclient.protocol.authentication_token = \
                    made.AuthenticationToken
                thief._server_nonce = done.ServerNonce
                with pytest.raises(UaStatusCodeError) as taken:
                    await activate(thief, encrypted_password(rig, done.ServerNonce))
                assert refused(taken, ua.StatusCodes.BadSecurityChecksFailed)
            rig.cert, rig.key = rig.tmp / "client" / "scada.der", rig.tmp / "client" / "scada.pem"
            async with channel(rig, port, Mode.SignAndEncrypt) as again:
                again.uaclient.protocol.authentication_token = \
                    made.AuthenticationToken
                again._server_nonce = done.ServerNonce
                await activate(again, encrypted_password(rig, done.ServerNonce))
                assert (await read_status(again, await namespace(again))).Value.Value == "ok"


@pytest.mark.anyio
async def test_nobody_registers_a_server_to_be_found_here(rig: Rig) -> None:
    """asyncua answers RegisterServer to anyone, without a session, and FindServers
    lists what was registered: a client could point others to a server of its own.
    The gateway is no discovery server: BadServiceUnsupported, and FindServers lists
    the gateway alone."""
    port = free_port()
    async with running(rig.config(port, allow_none=True)) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port) as client:
            fake = ua.RegisteredServer(ServerUri="urn:evil", IsOnline=True,
                                       ServerType=ua.ApplicationType.Server,
                                       DiscoveryUrls=["opc.tcp://127.0.0.1:1/"],
                                       ServerNames=[ua.LocalizedText("evil")])
            with pytest.raises(UaStatusCodeError) as unsupported:
                await client.uaclient.register_server(fake)
            assert refused(unsupported, ua.StatusCodes.BadServiceUnsupported)
            servers = await client.uaclient.find_servers(ua.FindServersParameters())
            assert [s.ApplicationUri for s in servers] == [f"urn:imu-gateway:{GID}"]


@pytest.mark.anyio
async def test_no_service_before_a_session_is_activated(rig: Rig) -> None:
    """asyncua's tracker has both (issues 1014 and 1156): a session created and never
    activated, or one whose activation was refused, reads nothing and calls nothing."""
    port = free_port()
    cfg = rig.config(port, anonymous=False, allow_commands=True,
                     users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.SignAndEncrypt) as client:
            made = await create_session(client)
            for attempt in ("never activated", "activation refused"):
                if attempt == "activation refused":
                    with pytest.raises(UaStatusCodeError):
                        await activate(client, encrypted_password(rig, made.ServerNonce,
                                                                  user="nobody"))
                with pytest.raises(UaStatusCodeError) as no_read:
                    await read_status(client)
                assert refused(no_read, ua.StatusCodes.BadSessionNotActivated), attempt
                with pytest.raises(UaStatusCodeError) as no_call:
                    await call_declination(client)
                assert refused(no_call, ua.StatusCodes.BadSessionNotActivated), attempt
    assert not rig.ah.writes_heard


@pytest.mark.anyio
async def test_a_password_the_endpoint_says_to_encrypt_is_refused_in_clear(rig: Rig) -> None:
    """On Basic256Sha256 Sign the endpoint's user token policy says the password is
    encrypted (the channel is not).  One sent in clear is BadIdentityTokenInvalid,
    even a right one; encrypted, the same password opens the session.  A token that
    names no policy of the endpoint is refused too."""
    port = free_port()
    cfg = rig.config(port, anonymous=False, allow_commands=True,
                     users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.Sign) as client:
            made = await create_session(client)
            with pytest.raises(UaStatusCodeError) as clear:
                await activate(client, clear_password())
            assert refused(clear, ua.StatusCodes.BadIdentityTokenInvalid)
            unnamed = encrypted_password(rig, made.ServerNonce)
            unnamed.PolicyId = "no-such-policy"
            with pytest.raises(UaStatusCodeError) as unknown:
                await activate(client, unnamed)
            assert refused(unknown, ua.StatusCodes.BadIdentityTokenInvalid)
            with pytest.raises(UaStatusCodeError) as anonymous:
                await activate(client, None)
            assert refused(anonymous, ua.StatusCodes.BadIdentityTokenInvalid,
                           ua.StatusCodes.BadIdentityTokenRejected)
            await activate(client, encrypted_password(rig, made.ServerNonce))
            assert (await read_status(client, await namespace(client))).Value.Value == "ok"
    assert not rig.ah.writes_heard


@pytest.mark.anyio
async def test_with_none_on_a_none_channel_works_as_documented(rig: Rig) -> None:
    """``allow_none: true``: the same hand-built session on a channel with no security
    is served, anonymously, and reads; a password goes encrypted for the server's
    certificate as the None endpoint's token policy says (in clear it is refused)."""
    port = free_port()
    cfg = rig.config(port, allow_none=True, users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port) as client:
            await create_session(client)
            done = await activate(client)
            ns = await namespace(client)
            assert (await read_status(client, ns)).Value.Value == "ok"
            with pytest.raises(UaStatusCodeError) as clear:
                await activate(client, clear_password())
            assert refused(clear, ua.StatusCodes.BadIdentityTokenInvalid)
            # (with the nonce of the latest activation: an older one would be a replay)
            await activate(client, encrypted_password(rig, done.ServerNonce))
            assert (await read_status(client, ns)).Value.Value == "ok"


# ------------------------------------------------------------------ the certificates

def _san(path: Path) -> tuple[set[str], set[str], set[str]]:
    """The URIs, DNS names and IP addresses a DER certificate names."""
    cert = x509.load_der_x509_certificate(path.read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return (set(names.get_values_for_type(x509.UniformResourceIdentifier)),
            set(names.get_values_for_type(x509.DNSName)),
            {str(a) for a in names.get_values_for_type(x509.IPAddress)})


def _interfaces() -> set[str]:
    """The host's addresses as ``ip`` lists them (not link-local), or none without it."""
    ip = shutil.which("ip")
    if ip is None:
        return set()
    out = subprocess.run([ip, "-o", "addr"], capture_output=True, text=True, check=True).stdout
    found = {line.split()[3].split("/")[0] for line in out.splitlines()}
    return {a for a in found if not ipaddress.ip_address(a).is_link_local}


@pytest.mark.anyio
async def test_the_server_certificate_names_the_address_clients_connect_to(rig: Rig) -> None:
    """Its application URI and host name, and the listen address; on 0.0.0.0 every
    address of the host.  A certificate the gateway made is made again when a name is
    missing (the address changed); one of your own is never replaced."""
    port = free_port()
    cert = rig.pki / "server_cert.der"
    async with running(rig.config(port)):
        uris, dns, ips = _san(cert)
    assert uris == {f"urn:imu-gateway:{GID}"} and socket.gethostname() in dns
    assert "127.0.0.1" in ips
    first = cert.read_bytes()
    async with running(rig.config(port)):
        assert cert.read_bytes() == first  # nothing missing: kept
    everywhere = rig.config(port)
    everywhere["opcua"]["listen"] = f"0.0.0.0:{port}"
    async with running(everywhere):
        _, _, ips = _san(cert)
    assert {"127.0.0.1", "::1"} | _interfaces() <= ips, ips
    # one of your own: kept as it is, whatever it names
    key = serialization.load_pem_private_key((rig.pki / "server_key.pem").read_bytes(), None)
    own = generate_self_signed_app_certificate(
        key, "plant CA made", {"organizationName": "Plant IT"},
        [x509.UniformResourceIdentifier(f"urn:imu-gateway:{GID}")],
        [ExtendedKeyUsageOID.SERVER_AUTH])
    cert.write_bytes(own.public_bytes(serialization.Encoding.DER))
    async with running(everywhere):
        assert cert.read_bytes() == own.public_bytes(serialization.Encoding.DER)


@pytest.mark.anyio
async def test_an_untrusted_client_certificate_waits_in_rejected_to_be_moved(
        rig: Rig) -> None:
    """As UaExpert and open62541 do: the refused certificate is saved in ``rejected/``;
    moved to ``trusted/``, it is accepted without a restart."""
    port = free_port()
    (rig.pki / "trusted" / "scada.der").unlink()
    cfg = rig.config(port, anonymous=False, users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.SignAndEncrypt) as client:
            with pytest.raises(UaStatusCodeError) as untrusted:
                await create_session(client)
            assert refused(untrusted, ua.StatusCodes.BadCertificateUntrusted)
        (saved,) = list((rig.pki / "rejected").iterdir())
        assert saved.read_bytes() == rig.cert.read_bytes() and "scada" in saved.name
        async with channel(rig, port, Mode.SignAndEncrypt) as again:  # (saved once)
            with pytest.raises(UaStatusCodeError):
                await create_session(again)
        assert len(list((rig.pki / "rejected").iterdir())) == 1
        saved.rename(rig.pki / "trusted" / saved.name)
        async with channel(rig, port, Mode.SignAndEncrypt) as trusted:
            made = await create_session(trusted)
            await activate(trusted, encrypted_password(rig, made.ServerNonce))
            assert (await read_status(trusted, await namespace(trusted))).Value.Value == "ok"


@pytest.mark.anyio
async def test_a_start_and_a_refused_flood_cost_the_log_a_few_lines(
        rig: Rig, caplog: pytest.LogCaptureFixture) -> None:
    """At the default level (INFO) asyncua said about a thousand lines at each start
    and one per Publish; and a client refused fifty times would cost a hundred lines."""
    caplog.set_level(logging.INFO)
    port = free_port()
    cfg = rig.config(port, anonymous=False, users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        started = [r for r in caplog.records if r.name.startswith(("asyncua", "imu_gateway"))]
        assert len(started) <= 10, [r.getMessage() for r in started]
        caplog.clear()
        async with channel(rig, port) as client:
            for _ in range(50):
                with pytest.raises(UaStatusCodeError):
                    await create_session(client)
        async with channel(rig, port, Mode.SignAndEncrypt) as secure:
            made = await create_session(secure)
            await activate(secure, encrypted_password(rig, made.ServerNonce))
            ns = await namespace(secure)
            for _ in range(50):
                await read_status(secure, ns)
    said = [r for r in caplog.records if r.name.startswith(("asyncua.server", "imu_gateway"))]
    # the gateway's line; asyncua's fault line once a minute in the process (an
    # earlier test may have had this minute's)
    for who, most in (("imu_gateway", 1), ("asyncua", 1)):
        refusals = [r for r in said if r.name.startswith(who)
                    and "BadSecurityModeRejected" in r.getMessage()]
        assert len(refusals) <= most, [r.getMessage() for r in said]
    assert any(r.name.startswith("imu_gateway") and "BadSecurityModeRejected"
               in r.getMessage() for r in said)
    assert len(said) <= 10, [r.getMessage() for r in said]
