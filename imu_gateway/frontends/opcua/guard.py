"""Who gets past the secure channel: the rules of OPC UA Part 4 (SecureChannel and
Session services) that asyncua 2.1's server leaves out, checked on each request before
asyncua sees it.

asyncua opens a channel with security mode None whether or not a None endpoint is
offered (its connection starts with the None policy and keeps it when nothing else
matches), serves sessions over that channel, takes a password in clear whatever the
endpoint's user token policy says, and lets any channel take a session over with its
authentication token.  So here:

* **A channel with no security, when None is not offered**, serves discovery only:
  GetEndpoints and FindServers (a client asks them before it picks a secured
  endpoint).  Every other request, CreateSession first, gets BadSecurityModeRejected.
* **ActivateSession:** the token must name (``PolicyId``) a user token policy of the
  endpoint the channel is on, of the token's type; a password that policy says to
  encrypt must come encrypted with the policy's algorithm.  Else
  BadIdentityTokenInvalid.
* **RegisterServer**, which asyncua serves to anyone without a session (and lists in
  FindServers), is BadServiceUnsupported: the gateway is no discovery server.
* **A session not activated** (never, or its activation was refused) gets
  BadSessionNotActivated for anything but discovery and the session services.
* **A session taken to another channel** (Part 4 5.6.3.1) must come with the client
  certificate it was created with: else BadSecurityChecksFailed.
* **CreateSession on a secured channel:** the certificate the channel was opened with
  must be the one the request names, and trusted (asyncua checks only the one the
  request names, and only when it names one).  A connection holds one session not
  yet activated: a second CreateSession closes the first, a refused one is closed.
* **An encrypted password** must end with the nonce the server gave its session
  (Part 4 7.41.2.3; asyncua drops it unread): a password seen once on a signed channel
  cannot be replayed.
* **Subscriptions:** at most ``MAX_SUBSCRIPTIONS_PER_SESSION`` a session, a
  publishing interval of at most ``MAX_PUBLISHING_INTERVAL_MS`` and a lifetime of at
  most ``MAX_SUBSCRIPTION_LIFETIME_S``; a closed session's subscriptions go with it
  (a client cannot leave them behind to hold the server's).
* **A subscription is its session's**: no other session may touch it or its items,
  nor take it over unless it acts for the same user (``ownership.py``).
* **Monitored items**: a new subscription's items get their queues as Part 4 has
  them and are sampled at their revised sampling intervals (``sampling.py``).
* **A message chunk** larger than the receive buffer is refused from its header, before
  its body is read (asyncua buffers a declared 4 GiB chunk as it arrives).

The hook is asyncua's own classes, one method each: :class:`GatewayUaServer` starts a
:class:`BinaryServer` whose connections get a :class:`GuardedProcessor`.
"""

from __future__ import annotations

import logging
import socket
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from asyncua import Server, ua
from asyncua.common.connection import SecureConnection
from asyncua.common.utils import Buffer, ServiceError
from asyncua.crypto import uacrypto
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256, SecurityPolicyNone
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_session import InternalSession
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary, struct_to_binary, uatcp_to_binary
from cryptography import x509

from ...supervise import PeerLog
from . import ownership
from .conditions import CALLER, Caller
from .sampling import SAMPLING_STEP_MS, EveryValue, sample_items

log = logging.getLogger("imu_gateway.opcua")

_DISCOVERY = frozenset({ua.ObjectIds.GetEndpointsRequest_Encoding_DefaultBinary,
                        ua.ObjectIds.FindServersRequest_Encoding_DefaultBinary})
_ACTIVATE = ua.NodeId(ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary)
_CREATE = ua.NodeId(ua.ObjectIds.CreateSessionRequest_Encoding_DefaultBinary)
#: A Local Discovery Server's services: asyncua serves them to anyone, with no session,
#: and FindServers then lists what was registered.  The gateway is no LDS.
_REGISTER = frozenset({ua.ObjectIds.RegisterServerRequest_Encoding_DefaultBinary,
                       ua.ObjectIds.RegisterServer2Request_Encoding_DefaultBinary})
_CLOSE = ua.NodeId(ua.ObjectIds.CloseSessionRequest_Encoding_DefaultBinary)
_SUBSCRIBE = ua.NodeId(ua.ObjectIds.CreateSubscriptionRequest_Encoding_DefaultBinary)
_MODIFY = ua.NodeId(ua.ObjectIds.ModifySubscriptionRequest_Encoding_DefaultBinary)
_PUBLISH = ua.NodeId(ua.ObjectIds.PublishRequest_Encoding_DefaultBinary)
_CALL = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
MAX_SUBSCRIPTIONS_PER_SESSION = 10
MAX_PUBLISHING_INTERVAL_MS = 60_000.0
MAX_SUBSCRIPTION_LIFETIME_S = 3600.0
#: What a session that is not activated may still ask.
_BEFORE_ACTIVATION = _DISCOVERY | {ua.ObjectIds.CreateSessionRequest_Encoding_DefaultBinary,
                                   ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary,
                                   ua.ObjectIds.CloseSessionRequest_Encoding_DefaultBinary}

#: The token types, by the policy type that admits them.
_TOKEN_TYPES: dict[type, ua.UserTokenType] = {
    ua.AnonymousIdentityToken: ua.UserTokenType.Anonymous,
    ua.UserNameIdentityToken: ua.UserTokenType.UserName,
    ua.X509IdentityToken: ua.UserTokenType.Certificate,
    ua.IssuedIdentityToken: ua.UserTokenType.IssuedToken,
}
#: How a password is encrypted under each security policy the gateway offers.
_PASSWORD_ENCRYPTION = {SecurityPolicyBasic256Sha256.URI:
                        SecurityPolicyBasic256Sha256.AsymmetricEncryptionURI}


@dataclass(frozen=True, slots=True)
class Watch:
    """What the connections of one server share: the client certificate each session
    was created with, the warnings about peers (a line a kind a minute; the owner
    flushes the counts held back), and the cache's ``catch_up``: the bus's turns wait
    for a reader (``Cache.catch_up``), and each request, publish and sampling tick is
    one; it also writes the newest samples into the address space
    (``writes.Samples``), by the register of the items that take every value
    (``every``)."""

    catch_up: Callable[[], None]
    every: EveryValue = field(default_factory=EveryValue)
    origins: weakref.WeakKeyDictionary[Any, bytes | None] = field(
        default_factory=weakref.WeakKeyDictionary)
    peers: PeerLog = field(default_factory=lambda: PeerLog(log))

    def refuse(self, code: int, why: str, peer: Any) -> ServiceError:
        name = ua.StatusCode(code).name
        self.peers.warning(name, "opcua: refused %s from %s (%s)", why, peer, name)
        return ServiceError(code)


def token_problem(token: Any, endpoint: ua.EndpointDescription | None) -> str | None:
    """Why ``token`` may not activate a session on ``endpoint`` (None: it may).  The
    endpoint is the one of the channel's policy and mode."""
    if endpoint is None:
        return "a session on a channel whose security no endpoint offers"
    if isinstance(token, ua.ExtensionObject) or token is None:
        # Part 4 5.6.3: a null token is anonymous
        token = ua.AnonymousIdentityToken()
        offered = [p for p in endpoint.UserIdentityTokens
                   if p.TokenType == ua.UserTokenType.Anonymous]
        return None if offered else "an anonymous session where the endpoint offers none"
    kind = _TOKEN_TYPES.get(type(token))
    policy = next((p for p in endpoint.UserIdentityTokens if p.PolicyId == token.PolicyId),
                  None)
    if kind is None or policy is None or policy.TokenType != kind:
        return (f"a {type(token).__name__} naming user token policy {token.PolicyId!r}, "
                "which the endpoint does not offer for it")
    if kind == ua.UserTokenType.UserName:
        under = policy.SecurityPolicyUri or endpoint.SecurityPolicyUri
        if under != SecurityPolicyNone.URI and \
                token.EncryptionAlgorithm != _PASSWORD_ENCRYPTION.get(under, "?"):
            return (f"user {token.UserName!r}'s password sent "
                    f"{'in clear' if not token.EncryptionAlgorithm else 'encrypted otherwise'}"
                    f" where the endpoint's token policy asks for {under}")
    return None


class GuardedProcessor(UaProcessor):
    """asyncua's processor of one connection, with the checks of this module first."""

    def __init__(self, *args: Any, watch: Watch) -> None:
        super().__init__(*args)
        self._none_offered = False
        self._watch = watch

    def set_policies(self, policies: list[Any]) -> None:
        super().set_policies(policies)
        self._none_offered = any(p.matches(SecurityPolicyNone.URI, ua.MessageSecurityMode.None_)
                                 for p in policies)

    @property
    def _channel(self) -> Any:
        connection: SecureConnection = self._connection
        return connection.security_policy

    async def _process_message(self, typeid: ua.NodeId, requesthdr: Any, seqhdr: Any,
                               body: Buffer) -> Any:
        channel = self._channel
        self._check_service(typeid, channel)
        if typeid == _CREATE:
            await self._check_creation(body.copy(), channel)
        elif typeid == _ACTIVATE:
            self._check_activation(requesthdr, body.copy(), channel)
        elif typeid == _SUBSCRIBE:
            self._check_share()
            body = _revised(ua.CreateSubscriptionParameters, body, fastest=0.0)
        elif typeid == _MODIFY:
            # (0 is asyncua's publish-on-change, which only a new subscription starts
            # right: a running one switched to it kept its queued values unsent)
            body = _revised(ua.ModifySubscriptionParameters, body, fastest=SAMPLING_STEP_MS)
        elif typeid == _CLOSE:
            body = Buffer(ua.ua_binary.Primitives.Boolean.pack(True))  # deleteSubscriptions
        elif typeid == _PUBLISH and self.session is not None and \
                await ownership.answer_notice(self, requesthdr, seqhdr, body.copy()):
            return True
        self._watch.catch_up()  # (a Read gives the newest sample the bus has)
        # a method learns who calls it from here (asyncua passes it only the object)
        caller = CALLER.set(self._caller()) if typeid == _CALL else None
        try:
            answer = await super()._process_message(typeid, requesthdr, seqhdr, body)
        except Exception:
            if typeid == _CREATE:
                await self._drop_pending()  # (asyncua registers it before its checks)
            raise
        finally:
            if caller is not None:
                CALLER.reset(caller)
        if typeid == _CREATE and self.session is not None:
            self._watch.origins[self.session] = channel.peer_certificate
            ownership.guard(self.session, self._watch.origins)
        elif typeid == _SUBSCRIBE and self.session is not None:
            sample_items(self.iserver.subscription_service, self.session.session_id,
                         MAX_PUBLISHING_INTERVAL_MS, self._watch.catch_up, self._watch.every)
        return answer

    def _caller(self) -> Caller | None:
        """The activated session's user name (None: anonymous), the peer's host and the
        session's id."""
        session = self.session
        if session is None or not session.is_activated():
            return None
        peer = self.name[0] if isinstance(self.name, tuple) and self.name else str(self.name)
        return Caller(getattr(session.user, "name", None), str(peer), session.session_id)

    def _check_service(self, typeid: ua.NodeId, channel: Any) -> None:
        standard = typeid.NamespaceIndex == 0
        if standard and typeid.Identifier in _REGISTER:
            raise self._watch.refuse(ua.StatusCodes.BadServiceUnsupported,
                          "RegisterServer (the gateway is no discovery server)", self.name)
        if channel.Mode == ua.MessageSecurityMode.None_ and not self._none_offered and \
                not (standard and typeid.Identifier in _DISCOVERY):
            raise self._watch.refuse(ua.StatusCodes.BadSecurityModeRejected,
                          f"request {typeid.to_string()} on a channel with security mode "
                          "None (it serves discovery only: opcua.allow_none is false)",
                          self.name)
        if self.session is not None and not self.session.is_activated() and \
                not (standard and typeid.Identifier in _BEFORE_ACTIVATION):
            # (asyncua refuses it too, as BadUserAccessDenied: Part 4 names this code)
            raise self._watch.refuse(ua.StatusCodes.BadSessionNotActivated,
                          f"request {typeid.to_string()} before its session was activated",
                          self.name)

    async def _drop_pending(self) -> None:
        """Close this connection's session if it was never activated."""
        pending: InternalSession | None = getattr(self, "session", None)
        if pending is not None and not pending.is_activated():
            await pending.close_session(True)
            self.session = None

    async def _check_creation(self, body: Buffer, channel: Any) -> None:
        await self._drop_pending()  # one session not yet activated per connection
        if channel.Mode == ua.MessageSecurityMode.None_:
            return  # no certificate to check (asyncua checks one the request names)
        params = struct_from_binary(ua.CreateSessionParameters, body)
        if params.ClientCertificate != channel.peer_certificate:
            raise self._watch.refuse(ua.StatusCodes.BadSecurityChecksFailed,
                                     "a CreateSession naming another certificate than its "
                                     "channel's", self.name)
        validator = self.iserver.certificate_validator
        if validator is not None:
            try:
                cert = x509.load_der_x509_certificate(channel.peer_certificate)
            except ValueError:
                raise self._watch.refuse(ua.StatusCodes.BadCertificateInvalid,
                              "a channel certificate that is no DER certificate",
                              self.name) from None
            await validator(cert, params.ClientDescription)

    def _check_activation(self, requesthdr: Any, body: Buffer, channel: Any) -> None:
        session = self.session
        if session is None:  # a session taken over from another channel
            session = self.iserver.lookup_external_session(requesthdr.AuthenticationToken)
            if session is not None and self._watch.origins.get(session) != channel.peer_certificate:
                raise self._watch.refuse(ua.StatusCodes.BadSecurityChecksFailed,
                              "a session taken to a channel of another client certificate",
                              self.name)
        params = struct_from_binary(ua.ActivateSessionParameters, body)
        endpoint = next((e for e in self.iserver.endpoints
                         if e.SecurityPolicyUri == channel.URI
                         and e.SecurityMode == channel.Mode), None)
        problem = token_problem(params.UserIdentityToken, endpoint) or \
            self._replay_problem(params.UserIdentityToken, session)
        if problem is not None:
            raise self._watch.refuse(ua.StatusCodes.BadIdentityTokenInvalid, problem, self.name)

    def _replay_problem(self, token: Any, session: InternalSession | None) -> str | None:
        """Why an encrypted password is not this session's (None: it is, or it is not
        encrypted: the token policy's check is ``token_problem``'s)."""
        if not isinstance(token, ua.UserNameIdentityToken) or not token.EncryptionAlgorithm \
                or session is None:
            return None
        secret = password_secret(self.iserver.private_key, token)
        nonce = session.nonce or b""
        if secret is None or not nonce or not secret.endswith(nonce):
            return (f"user {token.UserName!r}'s encrypted password, not made with this "
                    "session's nonce (a replay, or garbage)")
        return None

    def _check_share(self) -> None:
        """A new subscription within the session's share."""
        assert self.session is not None  # (activated: _check_service)
        mine = ownership.subscriptions_of(self.session,
                                          self.iserver.subscription_service.subscriptions)
        if mine >= MAX_SUBSCRIPTIONS_PER_SESSION:
            raise self._watch.refuse(ua.StatusCodes.BadTooManySubscriptions, f"a subscription over "
                          f"{MAX_SUBSCRIPTIONS_PER_SESSION} of one session", self.name)


def _revised(kind: Any, body: Buffer, fastest: float) -> Buffer:
    """A Create- or ModifySubscription's parameters within the limits, re-encoded for
    asyncua (which takes the publishing interval as asked); ``fastest``: what an
    interval of 0 or less (or NaN) becomes."""
    params = struct_from_binary(kind, body)
    interval = params.RequestedPublishingInterval
    if not fastest < interval <= MAX_PUBLISHING_INTERVAL_MS:  # (NaN too)
        interval = MAX_PUBLISHING_INTERVAL_MS if interval > fastest else fastest
    params.RequestedPublishingInterval = interval
    most = int(MAX_SUBSCRIPTION_LIFETIME_S * 1000 / max(interval, 1.0))
    params.RequestedLifetimeCount = max(3, min(params.RequestedLifetimeCount or most, most))
    params.RequestedMaxKeepAliveCount = max(1, min(
        params.RequestedMaxKeepAliveCount or 1, params.RequestedLifetimeCount // 3))
    return Buffer(struct_to_binary(params))


def password_secret(private_key: Any, token: ua.UserNameIdentityToken) -> bytes | None:
    """The password and nonce a UserNameIdentityToken's encrypted secret carries (Part 4
    7.41.2.3: a length, then the password and the server nonce); None: it cannot be
    decrypted, or its length does not fit."""
    decrypt = _DECRYPT.get(token.EncryptionAlgorithm)
    if decrypt is None or private_key is None or not token.Password:
        return None
    try:
        raw = decrypt(private_key, token.Password)
    except ValueError:
        return None
    length = int.from_bytes(raw[:4], "little", signed=True)
    return raw[4:4 + length] if 0 <= length <= len(raw) - 4 else None


_DECRYPT = {
    "http://www.w3.org/2001/04/xmlenc#rsa-1_5": uacrypto.decrypt_rsa15,
    "http://www.w3.org/2001/04/xmlenc#rsa-oaep": uacrypto.decrypt_rsa_oaep,
    "http://opcfoundation.org/UA/security/rsa-oaep-sha2-256": uacrypto.decrypt_rsa_oaep_sha256,
}


class _Protocol(OPCUAProtocol):
    watch: Watch
    refused = False  # a chunk too large came: what follows is dropped

    def connection_made(self, transport: Any) -> None:
        super().connection_made(transport)
        if self._transport() is not None:  # (None: refused, at max_connections)
            # asyncua makes its own processor here; ours replaces it before the first
            # byte is read (its message loop looks the processor up for each message)
            guarded = GuardedProcessor(self.iserver, self._transport(), self.limits,
                                       watch=self.watch)
            guarded.set_policies(self.policies)
            self.processor: UaProcessor | None = guarded

    def _transport(self) -> Any:
        return self.transport

    def data_received(self, data: bytes) -> None:
        if self.refused or \
                self._too_large(self._buffer + data[:8] if len(self._buffer) < 8 else self._buffer):
            return
        super().data_received(data)
        self._too_large(self._buffer)  # (the next chunk's header, behind whole ones)

    def _too_large(self, head: bytes) -> bool:
        """A chunk whose header declares more than the receive buffer is refused
        (BadTcpMessageTooLarge) and the connection closed, before its body comes."""
        transport = self._transport()
        if len(head) < 8 or transport is None:
            return False
        size = int.from_bytes(head[4:8], "little")
        if size <= self.limits.max_recv_buffer:
            return False
        self.watch.peers.warning(
            "BadTcpMessageTooLarge", "opcua: refused a %d-byte chunk from %s (the receive "
            "buffer is %d bytes); closed", size, self.peer_name, self.limits.max_recv_buffer)
        error = ua.ErrorMessage(ua.StatusCode(ua.StatusCodes.BadTcpMessageTooLarge),
                                "chunk larger than the receive buffer")
        transport.write(uatcp_to_binary(ua.MessageType.Error, error))
        transport.close()  # (asyncua's connection_lost then forgets it)
        self.refused, self._buffer = True, b""
        return True


class _BinaryServer(BinaryServer):
    def __init__(self, *args: Any, watch: Watch) -> None:
        super().__init__(*args)
        self.watch = watch

    def _make_protocol(self) -> OPCUAProtocol:
        protocol = _Protocol(iserver=self.iserver, policies=self._policies,
                             clients=self.clients, closing_tasks=self.closing_tasks,
                             limits=self.limits)
        protocol.watch = self.watch
        return protocol


class GatewayUaServer(Server):
    """asyncua's server, listening through :class:`_BinaryServer`."""

    def __init__(self, *args: Any, catch_up: Callable[[], None], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.watch = Watch(catch_up=catch_up)

    async def start(self) -> None:
        # asyncua's Server.start, with the one change of the binary server's class
        if self.iserver.certificate is not None:
            uacrypto.check_certificate(self.iserver.certificate, self._application_uri,
                                       socket.gethostname())
        await self._setup_server_nodes()
        await self.iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = _BinaryServer(self.iserver, host, port, self.limits,
                                         watch=self.watch)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except Exception:
            await self.iserver.stop()
            raise
