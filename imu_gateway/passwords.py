"""Password hashes for ``http.users`` (docs/rest.md, "Roles"): scrypt from the standard
library, written as one string, ``scrypt$n$r$p$salt$hash`` (salt and hash base64), which
``imu-gateway hash-password`` makes and the config keeps in place of the password."""

from __future__ import annotations

import base64
import functools
import hashlib
import hmac
import secrets

#: scrypt's cost: 2**14 × 8 × 128 bytes = 16 MiB and ~30 ms a check (measured on the
#: development machine): the scrypt paper's parameters for interactive logins, so a
#: stolen config's hashes cost a guesser as much per try, and a gateway on a small
#: box still answers a login at once.  (A hash keeps its parameters: raising them
#: later leaves older hashes valid.)
N, R, P = 2**14, 8, 1
PREFIX = "scrypt$"
_MAX_N = 2**20  # a hash from the config is trusted only this far (the memory it takes)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def hash_password(password: str, salt: bytes | None = None) -> str:
    salt = salt if salt is not None else secrets.token_bytes(16)
    digest = hashlib.scrypt(password.encode(), salt=salt, n=N, r=R, p=P, dklen=32)
    return f"{PREFIX}{N}${R}${P}${_b64(salt)}${_b64(digest)}"


def parse(stored: str) -> tuple[int, int, int, bytes, bytes]:
    """A hash's parts; ValueError naming what is wrong and how to make a good one."""
    parts = stored.split("$")
    fix = "make one with `imu-gateway hash-password`"
    if len(parts) != 6 or parts[0] != "scrypt":
        raise ValueError(f"not a password hash (scrypt$n$r$p$salt$hash): {fix}")
    try:
        n, r, p = (int(x) for x in parts[1:4])
        salt, digest = base64.b64decode(parts[4], validate=True), \
            base64.b64decode(parts[5], validate=True)
    except ValueError:
        raise ValueError(f"a damaged password hash: {fix}") from None
    if not (1 < n <= _MAX_N and n & (n - 1) == 0 and 0 < r <= 32 and 0 < p <= 16
            and salt and len(digest) >= 16):
        raise ValueError(f"a password hash with parameters out of range: {fix}")
    return n, r, p, salt, digest


def verify(password: str, stored: str) -> bool:
    """Whether ``password`` is the one ``stored`` was made from (constant time)."""
    n, r, p, salt, digest = parse(stored)
    given = hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, dklen=len(digest),
                           maxmem=2 * 128 * r * (n + p + 2))
    return hmac.compare_digest(given, digest)


@functools.cache
def dummy() -> str:
    """Checked against when the user name is unknown, so that an unknown name costs the
    same time as a wrong password (the time must not tell which names exist)."""
    return hash_password("", salt=b"\0" * 16)
