"""Logging in and out (docs/rest.md, "Roles"): ``POST /api/v1/login`` trades a user's
name and password (``http.users``) for a session token, or checks a token of
``http.tokens``; ``POST /api/v1/logout`` ends a session; ``GET /api/v1/me`` says whose
a credential is.  Login attempts are limited per client address."""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from datetime import UTC, datetime
from typing import Any, Self

from fastapi import FastAPI, Request, Response
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from ... import passwords
from ...errors import ErrorKind, RequestFailed
from .access import Authority, Credentials, Role, Roles, Who, error_response, peer_of
from .limits import API, LOGIN_WINDOW_S, LOGINS_PER_MINUTE
from .models import ErrorOut

log = logging.getLogger("imu_gateway.http")

#: Password checks at once: each takes scrypt's 16 MiB and ~30 ms of a core, and a
#: crowd of logins must not take the gateway's memory or its loop's workers.
_CHECKS_AT_ONCE = 2
#: Client addresses remembered by the limiter before the idle ones are forgotten.
_ADDRESSES = 4096


class LoginIn(BaseModel):
    """A user's name and password, or a token of ``http.tokens``."""

    model_config = ConfigDict(extra="forbid")

    user: str | None = Field(default=None, min_length=1, max_length=64,
                             description="a name of `http.users`")
    password: str | None = Field(default=None, max_length=1024, description="its password")
    token: str | None = Field(default=None, min_length=1, max_length=1024, description=(
        "instead of user and password: a token of `http.tokens` (or `http.token`), "
        "checked and given back"))

    @model_validator(mode="after")
    def _one_way(self) -> Self:
        if (self.token is None) == (self.user is None or self.password is None):
            raise ValueError("give user and password, or token")
        return self


class LoginOut(BaseModel):
    """The credential to send from now on, as ``Authorization: Bearer …``."""

    token: str = Field(description="a session token (the token given, for a token)")
    user: str = Field(description="the user's name, or which token it was")
    role: str = Field(description="`viewer`, `operator` or `admin`")
    expires_at: str | None = Field(description="when the session ends, ISO 8601 UTC "
                                   "(`null`: a token of the config, which does not expire)")


class WhoOut(BaseModel):
    """Whose the credential is."""

    user: str = Field(description="a user's name, which token, or `anonymous`")
    role: str = Field(description="`viewer`, `operator` or `admin`")


class Limiter:
    """At most ``LOGINS_PER_MINUTE`` attempts per address in any ``LOGIN_WINDOW_S``."""

    def __init__(self) -> None:
        self.attempts: dict[str, deque[float]] = {}

    def wait_s(self, address: str, now: float) -> float:
        """0: an attempt may be made now (and is counted); else how long until one may."""
        times = self.attempts.setdefault(address, deque())
        while times and times[0] <= now - LOGIN_WINDOW_S:
            times.popleft()
        if len(times) >= LOGINS_PER_MINUTE:
            return times[0] + LOGIN_WINDOW_S - now
        times.append(now)
        if len(self.attempts) > _ADDRESSES:  # forget who has not tried for a window
            for idle in [a for a, t in self.attempts.items() if t[-1] <= now - LOGIN_WINDOW_S]:
                del self.attempts[idle]
        return 0.0


def _iso(epoch: float) -> str:
    return datetime.fromtimestamp(epoch, UTC).isoformat(timespec="seconds").replace(
        "+00:00", "Z")


def login_routes(app: FastAPI, authority: Authority, roles: Roles) -> None:
    """``POST /api/v1/login``, ``POST /api/v1/logout``, ``GET /api/v1/me``."""
    limiter = Limiter()
    checks = asyncio.Semaphore(_CHECKS_AT_ONCE)

    async def user_of(name: str, password: str) -> Who | None:
        user = authority.config.users.get(name)
        async with checks:  # an unknown name costs as long as a wrong password
            good = await asyncio.to_thread(passwords.verify, password,
                                           user.password if user else passwords.dummy())
        return Who(name, Role[user.role.upper()]) if user and good else None

    @app.post(f"{API}/login", response_model=LoginOut, dependencies=[roles.public],
              responses={code: {"model": ErrorOut} for code in (401, 413, 422, 429)},
              tags=["login"], summary="a user's name and password for a session token (or a "
                                      "token checked); 5 attempts a minute per address")
    async def login(body: LoginIn, request: Request) -> JSONResponse:
        address = peer_of(request)
        wait = limiter.wait_s(address, time.monotonic())
        if wait > 0:
            log.warning("login: too many attempts from %s", address)
            response = error_response(RequestFailed(ErrorKind.TOO_MANY_ATTEMPTS, (
                f"{LOGINS_PER_MINUTE} login attempts a minute per address: try again in "
                f"{math.ceil(wait)} s")))
            response.headers["Retry-After"] = str(math.ceil(wait))
            return response
        if body.token is not None:
            who = authority.config_token(body.token)
            answer: dict[str, Any] = {"token": body.token, "expires_at": None}
        else:
            assert body.user is not None and body.password is not None  # (_one_way)
            who = await user_of(body.user, body.password)
            if who is not None:
                token, expires_at = authority.start_session(who)
                answer = {"token": token, "expires_at": _iso(expires_at)}
        if who is None:
            log.warning("login: refused %r from %s", body.user or "a token", address)
            raise RequestFailed(ErrorKind.UNAUTHORISED, "wrong user name or password"
                                if body.token is None else "no such token")
        log.info("login: %s (%s) from %s", who.name, who.role.label, address)
        return JSONResponse({**answer, "user": who.name, "role": who.role.label})

    @app.post(f"{API}/logout", status_code=204, dependencies=[roles.public], tags=["login"],
              summary="end this session (a token of the config stays valid)")
    async def logout(request: Request, credentials: Credentials) -> Response:
        ended = authority.end_session(credentials.credentials) if credentials else None
        if ended is not None:
            log.info("logout: %s from %s", ended.name, peer_of(request))
        return Response(status_code=204)

    @app.get(f"{API}/me", response_model=WhoOut, dependencies=[roles.public],
             responses={401: {"model": ErrorOut}}, tags=["login"],
             summary="whose this credential is, and its role")
    async def me(credentials: Credentials) -> dict[str, str]:
        if credentials is None and not authority.config.read_token_required:
            return {"user": "anonymous", "role": Role.VIEWER.label}
        who = authority.who(credentials.credentials if credentials else None)
        if who is None:
            raise RequestFailed(ErrorKind.UNAUTHORISED, "no such token, or the session "
                                "ended: log in again")
        return {"user": who.name, "role": who.role.label}

