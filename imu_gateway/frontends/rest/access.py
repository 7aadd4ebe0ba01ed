"""Who may do what, and how a refusal or an error is answered: the bearer token,
the body guard, the one error body, the security headers, and the request counter."""

from __future__ import annotations

import enum
import hmac
import logging
import secrets
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ...config import HttpConfig
from ...errors import ErrorKind, RequestFailed
from .limits import API, LOGIN_BODY, MAX_BODY

# Module level: FastAPI resolves the (string) annotations of endpoints here.
_bearer = HTTPBearer(auto_error=False, description="a token of http.tokens (or http.token), "
                     "or a session token from POST /api/v1/login")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]

log = logging.getLogger("imu_gateway.http")

#: The most sessions kept at once: beyond, the oldest ends (a flood of logins cannot
#: grow the gateway's memory).
MAX_SESSIONS = 1000


class Role(enum.IntEnum):
    """Who may do what (docs/rest.md, "Roles"); a higher role may do all a lower may.
    ``PUBLIC``: anyone, without a credential (the login itself, the API's index)."""

    PUBLIC = 0
    VIEWER = 1
    OPERATOR = 2
    ADMIN = 3

    @property
    def label(self) -> str:
        return self.name.lower()


@dataclass(frozen=True, slots=True)
class Who:
    """Who sent a request: for the log (``name``: a user, or which token, never the
    token itself) and for the rules (``role``)."""

    name: str
    role: Role


ANONYMOUS = Who("anonymous", Role.PUBLIC)


@dataclass(slots=True)
class _Session:
    who: Who
    ends: float  # time.monotonic()
    expires_at: float  # time.time(), for the answer


class Authority:
    """The credentials the gateway knows: the config's tokens, each with its role
    (``http.token``: an admin's), and the sessions of ``POST /api/v1/login``."""

    def __init__(self, config: HttpConfig) -> None:
        self.sessions: dict[str, _Session] = {}
        self.configure(config)

    def configure(self, config: HttpConfig) -> None:
        """Take ``config``'s credentials and rules, at once (a reload): a token no longer
        in it is refused from the next request on, and a session ends unless its user is
        still there with the same role and password (docs/rest.md, "Roles")."""
        old = getattr(self, "config", None)
        self.config = config
        self.tokens = [(token, Who("http.token" if token == config.token else
                                   f"token {i + 1} of http.tokens", Role[role.upper()]))
                       for i, (token, role) in enumerate(config.roles_of_tokens().items())]
        if old is not None:
            kept = {name for name, user in config.users.items()
                    if old.users.get(name) == user}
            self.sessions = {token: session for token, session in self.sessions.items()
                             if session.who.name in kept}

    @property
    def anybody_may_log_in(self) -> bool:
        return bool(self.tokens or self.config.users)

    def who(self, token: str | None) -> Who | None:
        """Whose ``token`` this is; ``None``: nobody's (or a session that ended)."""
        if token is None:
            return None
        found = self.config_token(token)
        if found is not None:
            return found
        session = self.sessions.get(token)
        if session is None:
            return None
        if session.ends <= time.monotonic():
            del self.sessions[token]
            return None
        return session.who

    def config_token(self, token: str) -> Who | None:
        """Whose token of the config ``token`` is (every one compared: the time tells
        nothing of how much of one matched)."""
        found = None
        for known, who in self.tokens:
            if hmac.compare_digest(token.encode(), known.encode()):
                found = who
        return found

    def start_session(self, who: Who) -> tuple[str, float]:
        """A new session token for ``who`` and when it expires (epoch seconds)."""
        now = time.monotonic()
        for token in [t for t, s in self.sessions.items() if s.ends <= now]:
            del self.sessions[token]
        while len(self.sessions) >= MAX_SESSIONS:
            del self.sessions[next(iter(self.sessions))]  # the oldest (insertion order)
        token = secrets.token_urlsafe(32)
        lasts = self.config.session_minutes * 60.0
        expires_at = time.time() + lasts
        self.sessions[token] = _Session(who, now + lasts, expires_at)
        return token, expires_at

    def end_session(self, token: str) -> Who | None:
        session = self.sessions.pop(token, None)
        return None if session is None else session.who

    def refusal(self, token: str | None, need: Role, commands: bool = False,
                ) -> tuple[Who, RequestFailed | None]:
        """Who sent ``token``, and why a request that needs ``need`` is refused, if
        it is (the one rule: the guard in front of a command's body and the routes'
        dependencies alike).  ``commands``: also needs ``http.allow_commands``."""
        who = self.who(token)
        if need is Role.PUBLIC or (need is Role.VIEWER and not self.config.read_token_required):
            return who or ANONYMOUS, None  # (a token nobody knows is ignored, as before)
        if commands and not self.config.allow_commands:
            return ANONYMOUS, RequestFailed(ErrorKind.FORBIDDEN,
                                            "commands are turned off (http.allow_commands)")
        if need > Role.VIEWER and not self.anybody_may_log_in:
            return ANONYMOUS, RequestFailed(ErrorKind.FORBIDDEN, (
                f"this needs the role {need.label}, and nobody has it: the config has no "
                "http.users, http.tokens or http.token"))
        if who is None:
            return ANONYMOUS, RequestFailed(ErrorKind.UNAUTHORISED, (
                "a valid bearer token is required: log in (POST /api/v1/login) or send a "
                "token of http.tokens"))
        if who.role < need:
            return who, RequestFailed(ErrorKind.FORBIDDEN, (
                f"{who.name} has the role {who.role.label}; this needs {need.label} "
                "(http.users, http.tokens)"))
        return who, None


class BodyGuard:
    """ASGI middleware that limits each request's body by its route: a command's is at
    most ``MAX_BODY`` bytes, a login's ``LOGIN_BODY``, the other routes (GET) take none
    (413 beyond, as soon as the headers say so).

    FastAPI reads and parses a body before it runs the route's dependencies, so
    without this an unauthorised client could make the gateway read a body of any
    size.  Here a command's access rules come first, then at most ``MAX_BODY`` bytes
    are read, and the body is handed on as it came."""

    def __init__(self, app: Any, authority: Authority) -> None:
        self.app, self.authority = app, authority

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method, on_command = scope["method"], _is_command(scope["path"])
        on_login = scope["path"] == f"{API}/login"
        command, login = method == "POST" and on_command, method == "POST" and on_login
        if not (command or login) and (on_command or on_login
                                       or method not in ("GET", "HEAD")):
            await self.app(scope, receive, send)  # no such route: 404 or 405, unread
            return
        headers = dict(scope["headers"])
        refusal = self._refusal(headers) if command else None
        limit = MAX_BODY if command else LOGIN_BODY if login else 0
        if refusal is None:
            refusal = _declared_too_large(scope, headers, limit)
        if refusal is not None:
            await error_response(refusal)(scope, receive, send)
            return
        if limit == 0:
            await self.app(scope, receive, send)
            return
        body = bytearray()
        more = True
        while more:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > limit:
                too_large = RequestFailed(ErrorKind.TOO_LARGE, f"the body is over {limit} bytes")
                await error_response(too_large)(scope, receive, send)
                return
        replayed = False

        async def replay() -> Any:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": bytes(body), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    def _refusal(self, headers: dict[bytes, bytes]) -> RequestFailed | None:
        return self.authority.refusal(bearer_of(headers), Role.OPERATOR, commands=True)[1]


def bearer_of(headers: dict[bytes, bytes]) -> str | None:
    """The token of an ``Authorization: Bearer …`` header."""
    scheme, _, token = headers.get(b"authorization", b"").decode("latin-1").partition(" ")
    return token if scheme.lower() == "bearer" and token else None


def _is_command(path: str) -> bool:
    return path.startswith(f"{API}/sensors/") and "/commands/" in path


def _declared_too_large(scope: Any, headers: dict[bytes, bytes],
                        limit: int) -> RequestFailed | None:
    """A body the headers announce over ``limit`` bytes (a chunked one has no size
    until it is read: only a route that takes none refuses it here)."""
    length = headers.get(b"content-length", b"0")
    chunked = b"transfer-encoding" in headers
    if (length.isdigit() and int(length) > limit) or (chunked and limit == 0):
        if limit == 0:
            return RequestFailed(ErrorKind.TOO_LARGE,
                                 f"{scope['method']} {scope['path']} takes no body")
        return RequestFailed(ErrorKind.TOO_LARGE, f"the body is over {limit} bytes")
    return None


def error_response(exc: RequestFailed) -> JSONResponse:
    """Every failed request's answer: ``{"error", "kind"}`` with the kind's status
    (``imu_gateway.errors.KINDS``), and the challenge with a 401."""
    return json_error(exc.status, exc.kind.value, str(exc))


def json_error(status: int, kind: str, message: str) -> JSONResponse:
    """An error answer of any status, the HTTP layer's own (404 of a path, 405) too."""
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse({"error": message, "kind": kind}, status, headers)


#: Every answer's: no MIME sniffing, and no Referer (a page's address is nobody else's
#: business).
ALWAYS = [(b"x-content-type-options", b"nosniff"), (b"referrer-policy", b"no-referrer")]
#: The pages' own scripts, styles and images only (the dashboard's icon is a data: URI);
#: nothing may frame them, and no form or <base> points elsewhere.
PAGE_POLICY = ("default-src 'self'; img-src 'self' data:; object-src 'none'; "
               "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
#: An answer that is data, not a page: it may load nothing, and nothing may frame it.
DATA_POLICY = "default-src 'none'; frame-ancestors 'none'"
#: The files that may be cached: they change only with the gateway's version.
CACHEABLE = ("/static/", "/docs/assets/")


class SecurityHeaders:
    """ASGI middleware adding the headers a browser needs to keep the dashboard and
    the API to themselves: ``ALWAYS``; a Content-Security-Policy (``pages``: the path
    of each HTML page and its policy, every other answer ``DATA_POLICY``); and
    ``Cache-Control: no-store`` on every answer but the static files (readings and
    settings must not stay in a browser's or a proxy's cache)."""

    def __init__(self, app: Any, pages: dict[str, str]) -> None:
        self.app, self.pages = app, pages

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        path = scope["path"]
        added = [*ALWAYS, (b"content-security-policy",
                           self.pages.get(path, DATA_POLICY).encode())]
        if not path.startswith(CACHEABLE):
            added.append((b"cache-control", b"no-store"))

        async def send_with(message: Any) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), *added]}
            await send(message)

        await self.app(scope, receive, send_with)


class CountRequests:
    """ASGI middleware counting HTTP requests (a plain one: Starlette's
    ``BaseHTTPMiddleware`` costs a task and a stream per request), and calling
    ``before()`` before each: the cache's ``catch_up``, so history, alarms and captures
    answer with every sample the buses have handed over."""

    def __init__(self, app: Any, counts: dict[str, int], before: Callable[[], None]) -> None:
        self.app, self.counts, self.before = app, counts, before

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] == "http":
            self.counts["requests"] += 1
            self.before()
        await self.app(scope, receive, send)


#: The role each dependency of ``Roles`` stands for: the OpenAPI document says it
#: (``x-role``), and a route without one is found by the tests.
_ROLE_OF: weakref.WeakKeyDictionary[Callable[..., Any], Role] = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class Roles:
    """One dependency per role: a route lists the one it needs, and nothing else
    decides who may call it (``dependencies=[roles.operator]``).  ``commands`` is an
    operator's that also needs ``http.allow_commands`` (commands and captures)."""

    public: Any
    viewer: Any
    operator: Any
    commands: Any
    admin: Any

    @classmethod
    def of(cls, authority: Authority) -> Roles:
        return cls(*(Depends(_checker(authority, need, commands)) for need, commands in (
            (Role.PUBLIC, False), (Role.VIEWER, False), (Role.OPERATOR, False),
            (Role.OPERATOR, True), (Role.ADMIN, False))))


def _checker(authority: Authority, need: Role, commands: bool) -> Callable[..., Any]:
    # async, like every dependency here: FastAPI runs a plain def in a worker thread,
    # a thread hop per request (measured: it halved the readings/s).
    async def check(request: Request, credentials: Credentials) -> None:
        who, refusal = authority.refusal(credentials.credentials if credentials else None,
                                         need, commands)
        if refusal is not None:
            raise refusal
        request.state.who = who
        if need is Role.ADMIN:  # every admin action, with who did it
            log.info("admin %s (%s): %s %s", who.name, peer_of(request), request.method,
                     request.url.path)

    _ROLE_OF[check] = need
    return check


def declared_role(route: APIRoute) -> Role | None:
    """The role a route needs, as its dependencies declare it (``None``: none does)."""
    roles = [_ROLE_OF[d.call] for d in route.dependant.dependencies
             if d.call is not None and d.call in _ROLE_OF]
    return max(roles) if roles else None


def who_of(request: Request) -> Who:
    """Who sent a request, as its role's dependency found (anonymous: nobody said)."""
    who: Who = getattr(request.state, "who", ANONYMOUS)
    return who


def peer_of(request: Request) -> str:
    return request.client.host if request.client else "unknown"
