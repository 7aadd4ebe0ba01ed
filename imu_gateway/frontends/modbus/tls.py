"""Modbus/TCP Security (Modbus.org MB-TCP-Security v21, docs/modbus-tcp.md): the TLS
port's context, the role in a client's certificate, and the right each request needs.

The connections themselves are ``server.py``'s: accepted in plain TCP (so the limits
on hostile clients reach a handshake in progress too), then upgraded by asyncio's
``start_tls``, so pipelining, deadlines and those limits hold on both ports.
What this module adds is decided once per connection (the role, from the certificate
the handshake verified) and checked once per request (``right_needed``).
"""

from __future__ import annotations

import logging
import ssl
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ...config.schema import ModbusRight, ModbusTlsConfig
from ...errors import StartupError
from . import ident

if TYPE_CHECKING:  # cryptography (9 MB) is imported when a TLS client is checked
    from cryptography import x509

log = logging.getLogger("imu_gateway.modbus")

#: The Modbus Role extension (its OID, dotted): its value is one ASN.1 UTF8String, the
#: role's name.
ROLE_OID = "1.3.6.1.4.1.50316.802.1"
#: A client that opened TCP must finish its handshake within this.  Until then it holds
#: a socket and a place of ``max_connections`` (and of its address's), the first place
#: given up to a newcomer; a real client needs milliseconds.
HANDSHAKE_TIMEOUT_S = 5.0
#: OpenSSL's TLS 1.2 suites, forward-secret ones first; the last is the suite the
#: specification names for every mbaps device (TLS_RSA_WITH_AES_128_CBC_SHA256), for
#: the PLCs that offer nothing else.  Its NULL (unencrypted) suite is never offered.
#: TLS 1.3's suites are OpenSSL's own and all kept.
CIPHERS = "ECDHE+AESGCM:ECDHE+CHACHA20:DHE+AESGCM:AES128-SHA256:!aNULL:!eNULL"

#: The right each function code needs on a sensor's unit and on unit 255 (a raw unit's
#: requests all need ``passthrough``).  Codes the server does not serve are listed with
#: the right they would need: a client without it learns nothing, not even that.
RIGHTS: dict[int, ModbusRight] = {
    1: "read", 2: "read", 3: "read", 4: "read", ident.FUNCTION: "read",
    5: "write", 6: "write", 15: "write", 16: "write", 23: "write",
}


def right_needed(function: int, raw_unit: bool) -> ModbusRight | None:
    """The right a request needs; None: a function nobody may use (answered 01)."""
    if function == ident.FUNCTION:  # answered from the config, raw units too
        return "read"
    return "passthrough" if raw_unit else RIGHTS.get(function)


def server_context(config: ModbusTlsConfig,
                   refused: Callable[[ssl.SSLError], None]) -> ssl.SSLContext:
    """Mutual TLS 1.2 or later, the client's certificate required and verified against
    ``ca_file``; ``refused`` hears of each handshake that fails.  Raises
    ``StartupError`` naming the file that cannot be used."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.sslobject_class = _watched(refused)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.verify_mode = ssl.CERT_REQUIRED
    # A client may not renegotiate (TLS 1.2; 1.3 has none).  Resumption stays on:
    # a resumed session keeps its verified certificate, so its role is read the same.
    context.options |= ssl.OP_NO_RENEGOTIATION
    context.set_ciphers(CIPHERS)
    try:
        context.load_cert_chain(config.certfile, config.keyfile)
    except (ssl.SSLError, OSError) as exc:
        raise StartupError(f"modbus.tls.certfile {config.certfile} / keyfile "
                           f"{config.keyfile}: cannot be used ({_reason(exc)}); both PEM, "
                           "the key unencrypted and the certificate's own") from None
    try:
        context.load_verify_locations(cafile=config.ca_file)
    except (ssl.SSLError, OSError) as exc:
        raise StartupError(f"modbus.tls.ca_file {config.ca_file}: cannot be used "
                           f"({_reason(exc)}); it must hold the CA's certificate, PEM") \
            from None
    return context


def _watched(refused: Callable[[ssl.SSLError], None]) -> type[ssl.SSLObject]:
    """The TLS object asyncio makes for each connection, telling ``refused`` of a
    failed handshake: asyncio itself says nothing of one, not even to the client (it
    closes the socket before the alert is sent), so without this a refused PLC and the
    gateway's log would both be silent about why."""
    class Watched(ssl.SSLObject):
        def do_handshake(self) -> None:
            try:
                super().do_handshake()
            except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
                raise
            except ssl.SSLError as exc:
                refused(exc)
                raise
    return Watched


#: OpenSSL's X509_V_ERR_UNHANDLED_CRITICAL_EXTENSION.
UNHANDLED_CRITICAL_EXTENSION = 34


def handshake_problem(exc: ssl.SSLError) -> str:
    """A refused handshake's cause for the log, with the likely fix."""
    if isinstance(exc, ssl.SSLCertVerificationError) \
            and exc.verify_code == UNHANDLED_CRITICAL_EXTENSION:
        # OpenSSL refuses it before the gateway sees the certificate, and does not say
        # which extension; the role's is the one a Modbus PKI adds, so it is named.
        return (f"its certificate has an extension marked critical that TLS does not "
                f"know ({exc.verify_message}): the Modbus Role extension "
                f"({ROLE_OID}) must not be critical; issue the certificate "
                "again without 'critical' on that extension")
    if isinstance(exc, ssl.SSLCertVerificationError):
        return (f"its certificate failed verification ({exc.verify_message}): is it "
                "signed by the CA of modbus.tls.ca_file, and still valid?")
    reason = exc.reason or str(exc)
    if reason == "PEER_DID_NOT_RETURN_A_CERTIFICATE":
        return "it sent no client certificate (Modbus/TCP Security requires one)"
    if "VERSION" in reason or "PROTOCOL" in reason:
        return f"no TLS version in common ({reason}): TLS 1.2 or later is required"
    return reason


def _reason(exc: Exception) -> str:
    return exc.reason if isinstance(exc, ssl.SSLError) and exc.reason else str(exc)


@dataclass(frozen=True, slots=True)
class Grant:
    """What one TLS client may do, decided at its handshake."""

    who: str  # the certificate's subject, for the log
    role: str | None  # as the certificate says it; None: no (readable) role
    rights: frozenset[ModbusRight]
    note: str  # why these rights, when they are not the role's own ("" when they are)


def grant_of(transport: Any, config: ModbusTlsConfig) -> Grant:
    """The rights of the client at the other end of a TLS transport (its certificate
    was verified by the handshake): its role's, else ``default_role``'s, else none."""
    from cryptography import x509

    ssl_object = transport.get_extra_info("ssl_object")
    der = ssl_object.getpeercert(binary_form=True) if ssl_object is not None else None
    if der is None:  # (CERT_REQUIRED: a handshake without one does not complete)
        return Grant("?", None, frozenset(), "no client certificate")
    who = "?"
    try:
        cert = x509.load_der_x509_certificate(der)
        who = cert.subject.rfc4514_string() or "an empty subject"
        role, problem = _role(cert)
    except (x509.DuplicateExtension, ValueError) as exc:
        # Two role extensions, or extensions that do not parse: which role was meant is
        # not known, and such a certificate is suspicious, so not even default_role.
        return Grant(who, None, frozenset(), f"its certificate's extensions are ambiguous "
                     f"({exc}): no rights, whatever default_role; issue it again with one "
                     "Modbus Role extension")
    if role is not None and role in config.roles:
        return Grant(who, role, frozenset(config.roles[role]), "")
    why = problem or (f"role {role!r} is not in modbus.tls.roles" if role is not None
                      else "no role extension")
    default = config.default_role
    rights = frozenset(config.roles[default]) if default is not None else frozenset()
    return Grant(who, role, rights, f"{why}: default_role {default or 'null (no rights)'}")


def _role(cert: x509.Certificate) -> tuple[str | None, str]:
    """The certificate's role, or None and what is wrong with its extension; raises
    ``x509.DuplicateExtension`` (two of any extension, two roles among them) or
    ``ValueError`` (extensions that do not parse): ``grant_of`` gives no rights then."""
    from cryptography import x509
    from cryptography.hazmat.asn1 import decode_der

    try:
        extension = cert.extensions.get_extension_for_oid(x509.ObjectIdentifier(ROLE_OID))
    except x509.ExtensionNotFound:
        return None, ""
    value = extension.value
    if not isinstance(value, x509.UnrecognizedExtension):  # (cryptography knows no such OID)
        return None, "role extension not readable"
    try:
        return decode_der(str, value.value), ""
    except ValueError:
        return None, "role extension is not one ASN.1 UTF8String"
