"""The OPC UA server's security: its certificate (made at the first start), the users
of the config, and the client certificates it trusts (``{pki_dir}/trusted``) or has
refused (``{pki_dir}/rejected``).

* Security mode None is offered only with ``allow_none``; Basic256Sha256 Sign and
  SignAndEncrypt always.
* A client that presents a certificate (every secured channel, and many clients in
  mode None too) must present one in the trust list; ``imu-gateway`` puts nothing
  there itself.
* The certificate the gateway makes names, besides its application URI and host name,
  the address it listens on, or every address of the host when it listens on all of
  them (a client that connects by IP address checks it).  It is made again when a name
  is missing, so after the host's addresses changed: clients then trust the new one.
  A certificate of your own (not made by the gateway) is never replaced.
* A client certificate refused as untrusted is saved in ``rejected/`` (at most
  ``MAX_REJECTED`` files): an administrator moves it to ``trusted/`` to accept it.
* Users and passwords come from the config (``${VAR}`` for the secrets); anonymous
  access is refused when ``anonymous: false`` (the config insists on that with
  commands on).
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import ipaddress
import itertools
import logging
import os
import socket
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import (
    dump_private_key_as_pem,
    generate_private_key,
    generate_self_signed_app_certificate,
)
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.hazmat.primitives import serialization

from ...config import OpcUaConfig

log = logging.getLogger("imu_gateway.opcua")

CERT, KEY, TRUSTED, REJECTED = "server_cert.der", "server_key.pem", "trusted", "rejected"
#: What rejected/ keeps: a client trying new (or padded) certificates fills no disk.
MAX_REJECTED, MAX_REJECTED_BYTES, MAX_CERTIFICATE_BYTES = 100, 1 << 20, 16 << 10
ORGANIZATION = "imu-gateway"  # the subject's O of a certificate the gateway made


class ConfigUsers:
    """asyncua's user manager: the config's users, and anonymous access if allowed."""

    def __init__(self, config: OpcUaConfig) -> None:
        self.users = dict(config.users)
        self.anonymous = config.anonymous

    def get_user(self, iserver: Any, username: str | None = None,
                 password: str | None = None, certificate: Any = None) -> User | None:
        if username is None:
            return User(role=UserRole.User) if self.anonymous else None
        expected = self.users.get(username)
        if expected is None or password is None or \
                not hmac.compare_digest(expected.encode(), password.encode()):
            log.warning("opcua: refused user %r (unknown user or wrong password)", username)
            return None
        return User(role=UserRole.User, name=username)


def policies(config: OpcUaConfig) -> list[ua.SecurityPolicyType]:
    secured = [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
               ua.SecurityPolicyType.Basic256Sha256_Sign]
    return [*secured, ua.SecurityPolicyType.NoSecurity] if config.allow_none else secured


def identity_tokens(config: OpcUaConfig) -> list[type]:
    tokens: list[type] = [ua.UserNameIdentityToken] if config.users else []
    return [ua.AnonymousIdentityToken, *tokens] if config.anonymous else tokens


def host_addresses(listen_host: str) -> list[str]:
    """The addresses a client may connect to: the one listened on, or the host's when
    it listens on all (``0.0.0.0``, ``::``, empty)."""
    if listen_host not in ("", "0.0.0.0", "::"):
        return [listen_host]
    found = {"127.0.0.1", "::1"}
    for family in (socket.AF_INET, socket.AF_INET6):
        try:
            infos = socket.getaddrinfo(socket.gethostname(), None, family)
        except OSError:
            continue
        found.update(str(info[4][0]).split("%")[0] for info in infos)
    found.update(_interface_addresses())
    return sorted(found)


def _interface_addresses() -> set[str]:
    """Every address of the host's interfaces (Linux: /proc/net; elsewhere none)."""
    found: set[str] = set()
    with contextlib.suppress(OSError, ValueError):
        for line in Path("/proc/net/if_inet6").read_text().splitlines():
            raw = line.split()[0]
            found.add(str(ipaddress.IPv6Address(bytes.fromhex(raw))))
    # IPv4: the table of local routes holds each interface's address
    with contextlib.suppress(OSError, ValueError):
        lines = Path("/proc/net/fib_trie").read_text().splitlines()
        for before, line in itertools.pairwise(lines):
            if "/32 host LOCAL" in line:
                found.add(before.split()[-1])
    return {a for a in found if not ipaddress.ip_address(a).is_link_local}


def _names(app_uri: str, addresses: list[str]) -> list[x509.GeneralName]:
    names: list[x509.GeneralName] = [x509.UniformResourceIdentifier(app_uri),
                                     x509.DNSName(socket.gethostname())]
    for address in addresses:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(address)))
        except ValueError:
            names.append(x509.DNSName(address))  # a host name to listen on
    return names


def _missing(cert: x509.Certificate, wanted: list[x509.GeneralName]) -> list[str]:
    """What ``cert`` lacks of a certificate the gateway would make now (its names, its
    time); empty when it is not the gateway's own."""
    made_here = cert.issuer == cert.subject and any(
        a.value == ORGANIZATION for a in cert.subject.get_attributes_for_oid(
            x509.NameOID.ORGANIZATION_NAME))
    if not made_here:
        return []
    if cert.not_valid_after_utc <= datetime.now(UTC):
        return ["validity (expired)"]
    try:
        have = set(cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value)
    except x509.ExtensionNotFound:
        have = set()
    return [str(getattr(n, "value", n)) for n in wanted if n not in have]


def ensure_certificate(pki: Path, app_uri: str, listen_host: str) -> tuple[Path, Path]:
    """The server's certificate and key in ``pki``: made when missing, expired, or
    (one the gateway made) lacking a name it would put in it now."""
    cert_file, key_file = pki / CERT, pki / KEY
    wanted = _names(app_uri, host_addresses(listen_host))
    if key_file.exists():
        key: Any = serialization.load_pem_private_key(key_file.read_bytes(), password=None)
    else:
        key = generate_private_key()
        # the server's identity: only its owner reads it, from the moment it exists
        fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as out:
            out.write(dump_private_key_as_pem(key))
    key_file.chmod(0o600)  # (one made by an earlier release, or by hand, too)
    why = "first start"
    if cert_file.exists():
        missing = _missing(x509.load_der_x509_certificate(cert_file.read_bytes()), wanted)
        if not missing:
            return cert_file, key_file
        why = f"it lacked {', '.join(missing)}"
    cert = generate_self_signed_app_certificate(
        key, f"imu-gateway {app_uri}", {"organizationName": ORGANIZATION}, wanted,
        [x509.oid.ExtendedKeyUsageOID.SERVER_AUTH], days=365)
    cert_file.write_bytes(cert.public_bytes(serialization.Encoding.DER))
    log.warning("opcua: made the server certificate %s (%s; valid one year, for %s): "
                "clients must trust it", cert_file, why,
                ", ".join(str(getattr(n, "value", n)) for n in wanted))
    return cert_file, key_file


async def secure(server: Server, config: OpcUaConfig, app_uri: str) -> Path:
    """Load (or make) the server's certificate, set the policies, users and trust list.
    Returns the certificate's path (the demo prints it)."""
    pki = Path(config.pki_dir)
    (pki / TRUSTED).mkdir(parents=True, exist_ok=True)
    (pki / REJECTED).mkdir(exist_ok=True)
    cert, key = ensure_certificate(pki, app_uri, config.listen.host)
    await server.load_certificate(str(cert))
    await server.load_private_key(str(key))
    server.set_security_policy(policies(config))
    server.set_identity_tokens(identity_tokens(config))
    server.set_certificate_validator(TrustList(pki / TRUSTED, pki / REJECTED))
    return cert


class TrustList:
    """The check of a client's certificate: in ``folder`` (or signed by a CA there),
    valid now, meant for a client.  The folder is read again when it changed, so a
    certificate put there is trusted without a restart.  Any certificate a client
    presents is checked, whatever the security mode: one the gateway cannot place is
    refused rather than half-trusted."""

    def __init__(self, folder: Path, rejected: Path) -> None:
        self.folder, self.rejected = folder, rejected
        self._seen: tuple[tuple[str, float], ...] | None = None
        self._check: CertificateValidator | None = None

    async def _load(self) -> None:
        files = tuple(sorted((p.name, p.stat().st_mtime) for p in self.folder.iterdir()
                             if p.suffix.lower() in (".der", ".pem", ".crt")))
        if files == self._seen:
            return
        self._seen, self._check = files, None
        if not files:
            log.warning("opcua: no client certificate in %s: a client presenting one is "
                        "refused until its certificate (DER or PEM) is put there", self.folder)
            return
        store = TrustStore([self.folder], [])
        await store.load()
        self._check = CertificateValidator(
            CertificateValidatorOptions.TRUSTED_VALIDATION
            | CertificateValidatorOptions.PEER_CLIENT, store)

    async def __call__(self, cert: Any, app_description: Any) -> None:
        await self._load()
        try:
            if self._check is None:
                raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
            await self._check(cert, app_description)
        except ServiceError as refused:
            if refused.code == ua.StatusCodes.BadCertificateUntrusted:
                self._keep(cert)
            raise

    def _keep(self, cert: x509.Certificate) -> None:
        """Save an untrusted client certificate in ``rejected/`` for an administrator
        to move to ``trusted/``."""
        der = cert.public_bytes(serialization.Encoding.DER)
        names = cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)
        label = "".join(c if c.isalnum() or c in "-_." else "_"
                        for c in str(names[0].value if names else "client"))[:60]
        target = self.rejected / f"{label} [{hashlib.sha1(der).hexdigest()}].der"
        with contextlib.suppress(OSError, ValueError):
            kept = list(self.rejected.iterdir())
            if target.exists() or len(der) > MAX_CERTIFICATE_BYTES or \
                    len(kept) >= MAX_REJECTED or \
                    sum(p.stat().st_size for p in kept) + len(der) > MAX_REJECTED_BYTES:
                return
            target.write_bytes(der)
            log.warning("opcua: refused an untrusted client certificate (%s); saved as %s: "
                        "move it to %s to trust it", label, target, self.folder)
