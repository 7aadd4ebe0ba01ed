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

The hook is asyncua's own classes, one method each: :class:`GatewayUaServer` starts a
:class:`BinaryServer` whose connections get a :class:`GuardedProcessor`.
"""

from __future__ import annotations

import logging
import socket
import weakref
from typing import Any

from asyncua import Server, ua
from asyncua.common.connection import SecureConnection
from asyncua.common.utils import Buffer, ServiceError
from asyncua.crypto import uacrypto
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256, SecurityPolicyNone
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_session import InternalSession
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary

from ...supervise import PeerLog

log = logging.getLogger("imu_gateway.opcua")

_DISCOVERY = frozenset({ua.ObjectIds.GetEndpointsRequest_Encoding_DefaultBinary,
                        ua.ObjectIds.FindServersRequest_Encoding_DefaultBinary})
_ACTIVATE = ua.NodeId(ua.ObjectIds.ActivateSessionRequest_Encoding_DefaultBinary)
_CREATE = ua.NodeId(ua.ObjectIds.CreateSessionRequest_Encoding_DefaultBinary)
#: A Local Discovery Server's services: asyncua serves them to anyone, with no session,
#: and FindServers then lists what was registered.  The gateway is no LDS.
_REGISTER = frozenset({ua.ObjectIds.RegisterServerRequest_Encoding_DefaultBinary,
                       ua.ObjectIds.RegisterServer2Request_Encoding_DefaultBinary})
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


#: The peer warnings of every guarded connection: a line a kind a minute (the server
#: flushes the counts held back, see ``OpcUaServer``).
PEERS = PeerLog(log)


def _refuse(code: int, why: str, peer: Any) -> ServiceError:
    name = ua.StatusCode(code).name
    PEERS.warning(name, "opcua: refused %s from %s (%s)", why, peer, name)
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

    def __init__(self, *args: Any, origins: weakref.WeakKeyDictionary[Any, bytes | None]
                 ) -> None:
        super().__init__(*args)
        self._none_offered = False
        self._origins = origins  # session -> the client certificate that created it

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
        if typeid.NamespaceIndex == 0 and typeid.Identifier in _REGISTER:
            raise _refuse(ua.StatusCodes.BadServiceUnsupported,
                          "RegisterServer (the gateway is no discovery server)", self.name)
        if channel.Mode == ua.MessageSecurityMode.None_ and not self._none_offered and \
                not (typeid.NamespaceIndex == 0 and typeid.Identifier in _DISCOVERY):
            raise _refuse(ua.StatusCodes.BadSecurityModeRejected,
                          f"request {typeid.to_string()} on a channel with security mode "
                          "None (it serves discovery only: opcua.allow_none is false)",
                          self.name)
        if self.session is not None and not self.session.is_activated() and \
                not (typeid.NamespaceIndex == 0 and typeid.Identifier in _BEFORE_ACTIVATION):
            # (asyncua refuses it too, as BadUserAccessDenied: Part 4 names this code)
            raise _refuse(ua.StatusCodes.BadSessionNotActivated,
                          f"request {typeid.to_string()} before its session was activated",
                          self.name)
        if typeid == _ACTIVATE:
            self._check_activation(requesthdr, body.copy(), channel)
        answer = await super()._process_message(typeid, requesthdr, seqhdr, body)
        if typeid == _CREATE and self.session is not None:
            self._origins[self.session] = channel.peer_certificate
        return answer

    def _check_activation(self, requesthdr: Any, body: Buffer, channel: Any) -> None:
        if self.session is None:  # a session taken over from another channel
            moved: InternalSession | None = self.iserver.lookup_external_session(
                requesthdr.AuthenticationToken)
            if moved is not None and self._origins.get(moved) != channel.peer_certificate:
                raise _refuse(ua.StatusCodes.BadSecurityChecksFailed,
                              "a session taken to a channel of another client certificate",
                              self.name)
        params = struct_from_binary(ua.ActivateSessionParameters, body)
        endpoint = next((e for e in self.iserver.endpoints
                         if e.SecurityPolicyUri == channel.URI
                         and e.SecurityMode == channel.Mode), None)
        problem = token_problem(params.UserIdentityToken, endpoint)
        if problem is not None:
            raise _refuse(ua.StatusCodes.BadIdentityTokenInvalid, problem, self.name)


class _Protocol(OPCUAProtocol):
    origins: weakref.WeakKeyDictionary[Any, bytes | None]

    def connection_made(self, transport: Any) -> None:
        super().connection_made(transport)
        if self.transport is not None:  # (None: refused, at max_connections)
            # asyncua makes its own processor here; ours replaces it before the first
            # byte is read (its message loop looks the processor up for each message)
            guarded = GuardedProcessor(self.iserver, self.transport, self.limits,
                                       origins=self.origins)
            guarded.set_policies(self.policies)
            self.processor: UaProcessor | None = guarded


class _BinaryServer(BinaryServer):
    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self._origins: weakref.WeakKeyDictionary[Any, bytes | None] = \
            weakref.WeakKeyDictionary()

    def _make_protocol(self) -> OPCUAProtocol:
        protocol = _Protocol(iserver=self.iserver, policies=self._policies,
                             clients=self.clients, closing_tasks=self.closing_tasks,
                             limits=self.limits)
        protocol.origins = self._origins
        return protocol


class GatewayUaServer(Server):
    """asyncua's server, listening through :class:`_BinaryServer`."""

    async def start(self) -> None:
        # asyncua's Server.start, with the one change of the binary server's class
        if self.iserver.certificate is not None:
            uacrypto.check_certificate(self.iserver.certificate, self._application_uri,
                                       socket.gethostname())
        await self._setup_server_nodes()
        await self.iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = _BinaryServer(self.iserver, host, port, self.limits)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except Exception:
            await self.iserver.stop()
            raise
