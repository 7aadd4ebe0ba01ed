"""Who may do what, and how a refusal or an error is answered: the bearer token,
the body guard, the one error body, the security headers, and the request counter."""

from __future__ import annotations

import hmac
from typing import Annotated, Any

from fastapi import Depends
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from ...config import HttpConfig
from ...errors import ErrorKind, RequestFailed
from .limits import API, MAX_BODY

# Module level: FastAPI resolves the (string) annotations of endpoints here.
_bearer = HTTPBearer(auto_error=False, description="the gateway's http.token")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


class BodyGuard:
    """ASGI middleware that limits each request's body by its route: a command's is at
    most ``MAX_BODY`` bytes, the other routes (GET) take none (413 beyond, as soon as
    the headers say so).

    FastAPI reads and parses a body before it runs the route's dependencies, so
    without this an unauthorised client could make the gateway read a body of any
    size.  Here a command's access rules come first, then at most ``MAX_BODY`` bytes
    are read, and the body is handed on as it came."""

    def __init__(self, app: Any, config: HttpConfig) -> None:
        self.app, self.config = app, config

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        method, on_command = scope["method"], _is_command(scope["path"])
        command = method == "POST" and on_command
        if not command and (on_command or method not in ("GET", "HEAD")):
            await self.app(scope, receive, send)  # no such route: 404 or 405, unread
            return
        headers = dict(scope["headers"])
        refusal = self._refusal(headers) if command else None
        if refusal is None:
            refusal = _declared_too_large(scope, headers, MAX_BODY if command else 0)
        if refusal is not None:
            await error_response(refusal)(scope, receive, send)
            return
        if not command:
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
            if len(body) > MAX_BODY:
                too_large = RequestFailed(ErrorKind.TOO_LARGE, f"the body is over {MAX_BODY} bytes")
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
        scheme, _, token = headers.get(b"authorization", b"").decode("latin-1").partition(" ")
        return command_refusal(self.config, token if scheme.lower() == "bearer" else None)


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


def token_matches(given: str, token: str | None) -> bool:
    """Constant time: how much of a token matched must not show in the answer's time."""
    return token is not None and hmac.compare_digest(given.encode(), token.encode())


def command_refusal(config: HttpConfig, token: str | None) -> RequestFailed | None:
    """Why a command with this bearer token is refused, if it is (the one rule, for
    the guard in front of the body and the routes' dependency alike)."""
    if not config.allow_commands:
        return RequestFailed(ErrorKind.FORBIDDEN, "commands are turned off (http.allow_commands)")
    if token is None or not token_matches(token, config.token):
        return RequestFailed(ErrorKind.UNAUTHORISED, "a valid bearer token is required")
    return None


def ack_refusal(config: HttpConfig, token: str | None) -> RequestFailed | None:
    """Why acknowledging an alarm with this bearer token is refused, if it is: it
    needs the token (an operator's right), whether or not commands are allowed."""
    if config.token is None:
        return RequestFailed(ErrorKind.FORBIDDEN, "acknowledging needs http.token (the "
                             "bearer token operators send); none is set")
    if token is None or not token_matches(token, config.token):
        return RequestFailed(ErrorKind.UNAUTHORISED, "a valid bearer token is required")
    return None


def error_response(exc: RequestFailed) -> JSONResponse:
    """Every failed request's answer: ``{"error", "kind"}`` with the kind's status
    (``imu_gateway.errors.KINDS``), and the challenge with a 401."""
    return json_error(exc.status, exc.kind.value, str(exc))


def json_error(status: int, kind: str, message: str) -> JSONResponse:
    """An error answer of any status, the HTTP layer's own (404 of a path, 405) too."""
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse({"error": message, "kind": kind}, status, headers)


#: Every answer's: no MIME sniffing, and no Referer (the dashboard's URL may carry the
#: token, ``?token=``, and its links must not hand it on).
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
    ``BaseHTTPMiddleware`` costs a task and a stream per request)."""

    def __init__(self, app: Any, counts: dict[str, int]) -> None:
        self.app, self.counts = app, counts

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] == "http":
            self.counts["requests"] += 1
        await self.app(scope, receive, send)
