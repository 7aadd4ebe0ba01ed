"""The OPC UA server's security: its certificate (made at the first start), the users
of the config, and the client certificates it trusts (``{pki_dir}/trusted``).

* Security mode None is offered only with ``allow_none``; Basic256Sha256 Sign and
  SignAndEncrypt always.
* A client that presents a certificate (every secured channel, and many clients in
  mode None too) must present one in the trust list; ``imu-gateway`` puts nothing
  there itself.
* Users and passwords come from the config (``${VAR}`` for the secrets); anonymous
  access is refused when ``anonymous: false`` (the config insists on that with
  commands on).
"""

from __future__ import annotations

import hmac
import logging
import socket
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography.x509.oid import ExtendedKeyUsageOID

from ...config import OpcUaConfig

log = logging.getLogger("imu_gateway.opcua")

CERT, KEY, TRUSTED = "server_cert.der", "server_key.pem", "trusted"


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


async def secure(server: Server, config: OpcUaConfig, app_uri: str) -> Path:
    """Load (or make) the server's certificate, set the policies, users and trust list.
    Returns the certificate's path (the demo prints it)."""
    pki = Path(config.pki_dir)
    (pki / TRUSTED).mkdir(parents=True, exist_ok=True)
    cert, key = pki / CERT, pki / KEY
    made = not cert.exists()
    await setup_self_signed_certificate(
        key, cert, app_uri, socket.gethostname(), [ExtendedKeyUsageOID.SERVER_AUTH],
        {"commonName": f"imu-gateway {app_uri}", "organizationName": "imu-gateway"})
    # The private key is the server's identity: only its owner reads it (asyncua
    # writes it with the umask's mode, often 0644).
    key.chmod(0o600)
    if made:
        log.info("opcua: made the server certificate %s (valid one year; clients must "
                 "trust it)", cert)
    await server.load_certificate(str(cert))
    await server.load_private_key(str(key))
    server.set_security_policy(policies(config))
    server.set_identity_tokens(identity_tokens(config))
    server.set_certificate_validator(TrustList(pki / TRUSTED))
    return cert


class TrustList:
    """The check of a client's certificate: in ``folder`` (or signed by a CA there),
    valid now, meant for a client.  The folder is read again when it changed, so a
    certificate put there is trusted without a restart.  Any certificate a client
    presents is checked, whatever the security mode: one the gateway cannot place is
    refused rather than half-trusted."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
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
        if self._check is None:
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
        await self._check(cert, app_description)
