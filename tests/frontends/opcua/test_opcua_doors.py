"""The OPC UA doors a hostile client tried (a review of the server, written apart from
it), each now shut: an untrusted certificate, a replayed password, sessions and
subscriptions left behind, a chunk that never ends, big certificates in rejected/,
odd tokens and odd encodings of a request's type.  Each test states what a client
should not get.  The hand-built client is test_opcua_security's (asyncua's low-level
client)."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.ua.uaerrors import UaStatusCodeError
from cryptography.x509.oid import ExtendedKeyUsageOID
from support.harness import free_port, running, until
from test_opcua_security import (
    GID,
    PASSWORD,
    Mode,
    Rig,
    activate,
    call_declination,
    channel,
    create_session,
    encrypted_password,
    made_rig,
    namespace,
    read_status,
)


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    async with made_rig(tmp_path) as r:
        yield r


async def _untrusted(rig: Rig, name: str = "intruder") -> tuple[Path, Path]:
    """A certificate and key nobody put in trusted/."""
    cert, key = rig.tmp / "client" / f"{name}.der", rig.tmp / "client" / f"{name}.pem"
    await setup_self_signed_certificate(
        key, cert, "urn:test:intruder", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH],
        {"commonName": name})
    return cert, key


@pytest.mark.anyio
@pytest.mark.parametrize("present", ["nothing", "a trusted client's certificate"])
async def test_an_untrusted_channel_certificate_gets_no_session(rig: Rig, present: str) -> None:
    """The trust list is checked by asyncua in CreateSession, on the certificate the
    request *carries* (``ClientCertificate``), and only when it carries one.  The
    channel's own certificate (the one whose key signs the channel and ActivateSession)
    is never checked.  A client with a certificate of its own making opens a
    Basic256Sha256 channel, then sends CreateSession with no certificate, or with a
    trusted client's certificate (public: it travels in clear in every OpenSecureChannel
    of that client).  Neither should get a session."""
    port = free_port()
    cfg = rig.config(port)  # the defaults: anonymous true, allow_none false
    trusted = rig.cert.read_bytes()
    rig.cert, rig.key = await _untrusted(rig)
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.SignAndEncrypt) as client:
            client.security_policy.host_certificate = \
                None if present == "nothing" else trusted  # (what CreateSession carries)
            got_in = True
            try:
                await create_session(client)
                await activate(client)
                status = await read_status(client, await namespace(client))
            except UaStatusCodeError:
                got_in = False
            assert not got_in, f"read {status.Value.Value!r} with an untrusted certificate"


@pytest.mark.anyio
async def test_an_untrusted_channel_with_a_password(rig: Rig) -> None:
    """The same with anonymous off and commands on: the certificate door is gone, the
    password is all that is left (the doc promises both)."""
    port = free_port()
    cfg = rig.config(port, anonymous=False, allow_commands=True, users={"operator": PASSWORD})
    rig.cert, rig.key = await _untrusted(rig)
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.SignAndEncrypt) as client:
            client.security_policy.host_certificate = None
            got_in = True
            try:
                made = await create_session(client)
                await activate(client, encrypted_password(rig, made.ServerNonce))
                await read_status(client, await namespace(client))
            except UaStatusCodeError:
                got_in = False
            assert not got_in


@pytest.mark.anyio
@pytest.mark.parametrize("who", ["trusted, never activating", "untrusted, refused"])
async def test_sessions_never_activated_are_gone_when_their_connection_is(
        rig: Rig, who: str) -> None:
    """asyncua's CreateSession makes and registers the session *before* it checks the
    client certificate, and a second CreateSession on the same connection replaces
    ``processor.session`` without closing the first.  A session never activated has no
    timeout task; the connection's close closes only the last one.  So every
    CreateSession but the last stays in ``iserver._external_sessions`` for good."""
    port = free_port()
    cfg = rig.config(port, anonymous=False, users={"operator": PASSWORD})
    if who.startswith("untrusted"):
        rig.cert, rig.key = await _untrusted(rig)
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        assert gw.opcua is not None and gw.opcua.server is not None
        server = gw.opcua.server
        iserver = server.iserver
        before = len(iserver._external_sessions)
        for _ in range(3):  # three connections, 100 CreateSession each
            async with channel(rig, port, Mode.SignAndEncrypt) as client:
                for _ in range(100):
                    with contextlib.suppress(UaStatusCodeError):
                        await create_session(client)
        await until(lambda: len(server.bserver.clients) == 0)
        leaked = len(iserver._external_sessions) - before
        assert leaked == 0, f"{leaked} sessions left behind by 3 closed connections"


@pytest.mark.anyio
@pytest.mark.parametrize("replayed_on", [Mode.Sign, Mode.None_])
async def test_an_encrypted_password_seen_once_is_not_good_twice(
        rig: Rig, replayed_on: ua.MessageSecurityMode) -> None:
    """Part 4 7.41.2.3: the encrypted password carries the server nonce of *its*
    session so that it cannot be replayed.  asyncua decrypts it and drops the nonce
    unread (internal_server.decrypt_user_token).  On a Sign channel (offered always)
    the token travels readable: an eavesdropper replays it in a session of its own,
    here on a Sign channel of a trusted certificate, and (allow_none: true) on a
    channel with no security and no certificate at all."""
    port = free_port()
    cfg = rig.config(port, allow_none=True, anonymous=False, allow_commands=True,
                     users={"operator": PASSWORD})
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.Sign) as victim:
            made = await create_session(victim)
            seen = encrypted_password(rig, made.ServerNonce)  # as it went on the wire
            await activate(victim, seen)
        async with channel(rig, port, replayed_on) as thief:
            await create_session(thief)  # another session, another nonce
            got_in = True
            try:
                await activate(thief, seen)
                called = await call_declination(thief, await namespace(thief))
            except UaStatusCodeError:
                got_in = False
            assert not got_in, f"logged in as operator by replay; set_declination: {called}"


async def _subscribe(client: Client, interval: float) -> ua.CreateSubscriptionResult:
    params = ua.CreateSubscriptionParameters(
        RequestedPublishingInterval=interval, RequestedLifetimeCount=15000,
        RequestedMaxKeepAliveCount=5000, MaxNotificationsPerPublish=0,
        PublishingEnabled=True, Priority=0)
    result: ua.CreateSubscriptionResult = await client.uaclient.create_subscription(
        params, lambda *_: None)
    return result


@pytest.mark.anyio
async def test_one_anonymous_client_leaves_no_one_a_subscription(rig: Rig) -> None:
    """asyncua caps subscriptions server-wide (1000) with no cap per session, takes the
    publishing interval as asked, and keeps the subscriptions of a session closed with
    deleteSubscriptions=false (asyncua issue 1982) for LifetimeCount x interval.  An
    anonymous client (the default config) took all 1000 with an interval of ~31 years
    and left: every client after it was refused, until a restart.  Now a session holds
    at most its share, its interval and lifetime are bounded, and a closed session's
    subscriptions go with it."""
    port = free_port()
    async with running(rig.config(port)) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        assert gw.opcua is not None and gw.opcua.server is not None
        held = gw.opcua.server.iserver.subscription_service.subscriptions
        async with channel(rig, port, Mode.SignAndEncrypt) as hog:
            await create_session(hog)
            await activate(hog)
            got: list[ua.CreateSubscriptionResult] = []
            with pytest.raises(UaStatusCodeError) as enough:
                for _ in range(1000):
                    got.append(await _subscribe(hog, 1e12))
            assert enough.value.code == ua.StatusCodes.BadTooManySubscriptions
            assert 0 < len(got) <= 10
            for result in got:
                assert result.RevisedPublishingInterval <= 60_000
                lifetime = result.RevisedPublishingInterval * result.RevisedLifetimeCount
                assert lifetime <= 3600 * 1000, lifetime
            await hog.uaclient.close_session(delete_subscriptions=False)
        assert not held, f"{len(held)} subscriptions left by a closed session"
        async with channel(rig, port, Mode.SignAndEncrypt) as scada:
            await create_session(scada)
            await activate(scada)
            assert (await _subscribe(scada, 100.0)).RevisedPublishingInterval == 100.0


@pytest.mark.anyio
async def test_odd_tokens_and_odd_encodings_get_nothing(rig: Rig) -> None:
    """Attempts that should all be refused (and were): X509 and Issued tokens naming the
    user name policy or their own; a garbage 'encrypted' password; the Read request's
    type id in FourByte, String and other-namespace encodings on a session not yet
    activated and on a None channel; a forged AuthenticationToken."""
    from asyncua.ua.ua_binary import struct_to_binary
    port = free_port()
    cfg = rig.config(port, anonymous=False, users={"operator": PASSWORD})
    outcomes: dict[str, str] = {}

    async def attempt(name: str, job) -> None:  # type: ignore[no-untyped-def]
        try:
            await job
            outcomes[name] = "SERVED"
        except UaStatusCodeError as exc:
            outcomes[name] = type(exc).__name__
        except Exception as exc:
            outcomes[name] = f"{type(exc).__name__}: {exc}"[:80]

    async def raw(client, typeid: ua.NodeId, body: bytes) -> None:  # type: ignore[no-untyped-def]
        # a request whose type id is encoded as the test says
        proto = client.uaclient.protocol
        request = ua.ReadRequest()
        request.Parameters.NodesToRead = [ua.ReadValueId(
            NodeId=ua.NodeId(ua.ObjectIds.Server_NamespaceArray),
            AttributeId=ua.AttributeIds.Value)]
        encoded = struct_to_binary(request)
        encoded = body + encoded[4:]  # replace the FourByte type id (4 bytes) by ours
        proto._request_id += 1
        future = asyncio.get_running_loop().create_future()
        proto._callbackmap[proto._request_id] = future
        msg = proto._connection.message_to_binary(
            encoded, message_type=ua.MessageType.SecureMessage, request_id=proto._request_id)
        proto.transport.write(msg)
        data = await asyncio.wait_for(future, 5)
        typeid_back = ua.ua_binary.nodeid_from_binary(data)
        if typeid_back != ua.NodeId(ua.ObjectIds.ReadResponse_Encoding_DefaultBinary):
            fault = ua.ua_binary.struct_from_binary(ua.ResponseHeader, data)
            raise UaStatusCodeError(fault.ServiceResult.value)

    import asyncio
    import struct
    encodings = {
        "Numeric (4-byte id)": b"\x02\x00\x00" + struct.pack("<I", 631),
        "FourByte": b"\x01\x00" + struct.pack("<H", 631),
        "String '631'": b"\x03\x00\x00" + struct.pack("<i", 3) + b"631",
        "Numeric ns=1": b"\x02\x01\x00" + struct.pack("<I", 631),
    }
    async with running(cfg) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        async with channel(rig, port, Mode.SignAndEncrypt) as client:
            made = await create_session(client)
            for name, prefix in encodings.items():
                await attempt(f"Read as {name}, not activated", raw(client, None, prefix))
            cert = rig.cert.read_bytes()
            await attempt("X509 token (username policy)", activate(
                client, ua.X509IdentityToken(PolicyId="username", CertificateData=cert)))
            await attempt("X509 token (own policy)", activate(
                client, ua.X509IdentityToken(PolicyId="certificate", CertificateData=cert)))
            await attempt("Issued token", activate(client, ua.IssuedIdentityToken(
                PolicyId="username", TokenData=b"x" * 64,
                EncryptionAlgorithm="http://www.w3.org/2001/04/xmlenc#rsa-oaep")))
            garbage = encrypted_password(rig, made.ServerNonce)
            garbage.Password = b"\x01" * 256
            await attempt("garbage encrypted password", activate(client, garbage))
            await attempt("Read after all that", read_status(client))
            await attempt("activate properly", activate(
                client, encrypted_password(rig, made.ServerNonce)))
            for name, prefix in encodings.items():
                await attempt(f"Read as {name}, activated", raw(client, None, prefix))
        async with channel(rig, port) as plain:
            plain.uaclient.protocol.authentication_token = made.AuthenticationToken
            for name, prefix in encodings.items():
                await attempt(f"Read as {name}, None channel", raw(plain, None, prefix))
    print()
    for name, outcome in outcomes.items():
        print(f"  {name:45} {outcome}")
    served = {n for n, o in outcomes.items() if o == "SERVED"}
    assert served <= {"activate properly", "Read as Numeric (4-byte id), activated",
                      "Read as FourByte, activated"}, served


@pytest.mark.anyio
async def test_rejected_holds_little_whatever_the_certificates_weigh(rig: Rig) -> None:
    """rejected/ keeps at most 100 files "so that a client trying new certificates fills
    no disk"; but a file is as big as the certificate a CreateSession carries, and a
    request may be 100 MiB (asyncua's max_message_size).  Anyone may open a channel
    (OpenSecureChannel checks no trust) and send CreateSession: here five certificates
    of 20 MiB each (one unrecognised extension of padding)."""
    import datetime

    from cryptography import x509 as cx509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import rsa
    port = free_port()
    rig.cert, rig.key = await _untrusted(rig)  # the channel's: any will do
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    now = datetime.datetime.now(datetime.UTC)
    async with running(rig.config(port)) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        for i in range(5):
            name = cx509.Name([cx509.NameAttribute(cx509.NameOID.COMMON_NAME, f"fat{i}")])
            fat = (cx509.CertificateBuilder().subject_name(name).issuer_name(name)
                   .public_key(key.public_key()).serial_number(cx509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(hours=1))
                   .not_valid_after(now + datetime.timedelta(days=1))
                   .add_extension(cx509.SubjectAlternativeName(
                       [cx509.UniformResourceIdentifier("urn:test:scada")]), False)
                   .add_extension(cx509.KeyUsage(True, True, True, True, False, False, False,
                                                 False, False), True)
                   .add_extension(cx509.ExtendedKeyUsage(
                       [cx509.oid.ExtendedKeyUsageOID.CLIENT_AUTH]), False)
                   .add_extension(cx509.UnrecognizedExtension(
                       cx509.ObjectIdentifier("1.3.6.1.4.1.99999.1"), b"\0" * (20 << 20)), False)
                   .sign(key, hashes.SHA256()))
            async with channel(rig, port, Mode.SignAndEncrypt) as client:
                client.security_policy.host_certificate = fat.public_bytes(
                    serialization.Encoding.DER)
                try:
                    await create_session(client)
                except Exception as exc:
                    print("\n  CreateSession:", type(exc).__name__, str(exc)[:150])
        size = sum(p.stat().st_size for p in (rig.pki / "rejected").iterdir())
        print(f"\n  rejected/: {len(list((rig.pki / 'rejected').iterdir()))} files, "
              f"{size / 2**20:.0f} MiB")
        assert size < 1 << 20


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _stream_forever(port: int, megabytes: int) -> tuple[int, bytes]:
    """A Hello whose header says 4 GiB, then zeros: how many MiB went, and what the
    server said before it closed."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall(b"HELF" + struct.pack("<I", 0xFFFFFFF0))
        block, sent = b"\0" * (1 << 20), 0
        with contextlib.suppress(OSError):
            for _ in range(megabytes):
                sock.sendall(block)
                sent += 1
        said = b""
        with contextlib.suppress(OSError):
            said = sock.recv(64)
        return sent, said


@pytest.mark.anyio
async def test_a_chunk_that_never_ends_is_refused_from_its_header(rig: Rig) -> None:
    """asyncua kept every byte of a chunk until the whole of it, as its header declares
    it (up to 4 GiB), had come: eight clients took 445 MiB and stalled the event loop
    every front end shares.  Now the header is enough: an Error (BadTcpMessageTooLarge),
    the connection closed, and the gateway holds nothing of it."""
    port = free_port()
    async with running(rig.config(port)) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        before = _rss_mb()
        sent, said = await asyncio.to_thread(_stream_forever, port, 64)
        grown = _rss_mb() - before
    assert sent < 64, "the gateway read 64 MiB of one chunk"
    assert said[:4] in (b"ERRF", b""), said  # (a reset may come before the Error is read)
    if said[:4] == b"ERRF":
        (code,) = struct.unpack("<I", said[8:12])
        assert code == ua.StatusCodes.BadTcpMessageTooLarge
    assert grown < 16, f"the gateway grew {grown:.0f} MiB"


def _watch(item: int, node: ua.NodeId, queue: int,
           attribute: int = ua.AttributeIds.Value) -> ua.MonitoredItemCreateRequest:
    return ua.MonitoredItemCreateRequest(
        ItemToMonitor=ua.ReadValueId(NodeId=node, AttributeId=attribute),
        MonitoringMode=ua.MonitoringMode.Reporting,
        RequestedParameters=ua.MonitoringParameters(
            ClientHandle=item, SamplingInterval=0.0, QueueSize=queue, DiscardOldest=True,
            Filter=ua.EventFilter() if attribute == ua.AttributeIds.EventNotifier else None))


@pytest.mark.anyio
async def test_a_client_that_asks_the_default_queue_holds_one_value(rig: Rig) -> None:
    """Part 4 7.21: a value item's requested queueSize 0 or 1 is one value, the newest.
    asyncua made 0 its cap, 10 000: a client asking the default and publishing slowly
    (or never) had every sample of every item queued for it, and then encoded.  An
    event item's 0 is the server's default; nothing is more than the gateway's cap."""
    port = free_port()
    async with running(rig.config(port)) as gw:
        await until(lambda: gw.cache.snapshot("boom").seq >= 1)
        assert gw.opcua is not None and gw.opcua.server is not None
        subscriptions = gw.opcua.server.iserver.subscription_service.subscriptions
        async with channel(rig, port, Mode.SignAndEncrypt) as slow:
            await create_session(slow)
            await activate(slow)
            ns = await namespace(slow)
            sub = (await _subscribe(slow, 60_000.0)).SubscriptionId  # no publish comes
            sequence = ua.NodeId(f"{GID}.Sensors.boom.Sequence", ns)
            server = ua.NodeId(ua.ObjectIds.Server)
            made = await slow.uaclient.create_monitored_items(ua.CreateMonitoredItemsParameters(
                SubscriptionId=sub, TimestampsToReturn=ua.TimestampsToReturn.Both,
                ItemsToCreate=[_watch(1, sequence, 0), _watch(2, sequence, 1),
                               _watch(3, sequence, 5), _watch(4, sequence, 10**6),
                               _watch(5, server, 0, ua.AttributeIds.EventNotifier)]))
            assert all(m.StatusCode.is_good() for m in made), made
            assert [m.RevisedQueueSize for m in made] == [1, 1, 5, 1000, 1000]
            seq = gw.cache.snapshot("boom").seq
            await until(lambda: gw.cache.snapshot("boom").seq >= seq + 8)
            queued = subscriptions[sub]._triggered_datachanges
            ids = [m.MonitoredItemId for m in made]
            assert [len(queued[i]) for i in ids[:3]] == [1, 1, 5]
            newest = queued[ids[0]][0].Value.Value.Value
            assert newest == queued[ids[2]][-1].Value.Value.Value  # the newest kept
            changed = await slow.uaclient.modify_monitored_items(
                ua.ModifyMonitoredItemsParameters(
                    SubscriptionId=sub, ItemsToModify=[
                        ua.MonitoredItemModifyRequest(
                            MonitoredItemId=i, RequestedParameters=ua.MonitoringParameters(
                                ClientHandle=n, QueueSize=0))
                        for n, i in enumerate((ids[2], ids[4]))]))
            assert [c.RevisedQueueSize for c in changed] == [1, 1000]
