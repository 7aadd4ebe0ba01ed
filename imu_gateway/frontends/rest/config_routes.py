"""The config over REST (docs/rest.md, "The config"): ``GET /api/v1/config`` shows it
as written, secrets hidden (``?format=yaml``: as YAML text); ``PUT /api/v1/config``
checks a new one, applies it as a reload, and saves it to the file (``?dry_run=1``:
the problems and the diff only); ``GET /api/v1/config/schema`` is the config's JSON
Schema, which the Setup page (``/setup``, docs/dashboard.md) builds its forms from."""

from __future__ import annotations

import functools
import io
from importlib import resources
from typing import Annotated, Any, Literal, Protocol, runtime_checkable

from fastapi import FastAPI, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response
from starlette.background import BackgroundTask

from ...config import GatewayConfig
from ...config.loading import copy_plain, parse_text
from ...errors import ConfigError, ErrorKind, RequestFailed
from ..common import GatewayLike
from .access import Roles
from .limits import API
from .models import ErrorOut

#: The largest config a PUT may send (a config of 250 sensors is about 40 kB).
MAX_CONFIG_BODY = 1 << 20


@runtime_checkable
class _Reloader(Protocol):
    def shown(self) -> Any: ...

    async def put(self, data: Any, dry_run: bool) -> Any: ...


def _reloader(gateway: GatewayLike) -> _Reloader:
    reloader = getattr(gateway, "reloader", None)
    if not isinstance(reloader, _Reloader):
        raise RequestFailed(ErrorKind.NOT_FOUND, "this gateway cannot change its config")
    return reloader


@functools.cache
def config_schema() -> dict[str, Any]:
    """The config's JSON Schema, from the pydantic models: the one source of the
    Setup page's forms and of docs/config-reference.md (each field's ``description``)."""
    return GatewayConfig.model_json_schema()


def as_yaml(data: Any) -> str:
    """The config's data as YAML text, in its key order (ruamel.yaml: it also writes
    the scalar types that its round trip reads the file into)."""
    from ruamel.yaml import YAML  # (only the Setup page's YAML tab needs it)

    out = io.StringIO()
    dumper = YAML(typ="rt")
    dumper.default_flow_style = False
    dumper.dump(copy_plain(data), out)
    return out.getvalue()


def config_routes(app: FastAPI, gateway: GatewayLike, roles: Roles) -> None:
    """``GET`` and ``PUT /api/v1/config``: both an admin's; the schema, a viewer's;
    the Setup page."""
    responses: dict[int | str, dict[str, Any]] = {
        code: {"model": ErrorOut} for code in (401, 403, 404, 413)}

    shown_as: dict[int | str, dict[str, Any]] = {200: {"content": {
        "application/json": {"schema": {"type": "object"}},
        "application/yaml": {"schema": {"type": "object"}}}}}  # (the config itself)

    @app.get(f"{API}/config", dependencies=[roles.admin], responses={**responses, **shown_as},
             summary="the config as written: every secret as its ${VAR} reference, or ***",
             tags=["config"])
    async def get_config(
        format: Annotated[Literal["json", "yaml"], Query(
            description="json: {\"config\": …}; yaml: the config as YAML text")] = "json",
    ) -> Response:
        shown = _reloader(gateway).shown()
        if format == "yaml":
            return Response(as_yaml(shown), media_type="application/yaml; charset=utf-8")
        return JSONResponse({"config": shown})

    # A viewer's: it is the documentation of every key (docs/config-reference.md is
    # generated from the same models), nothing of this gateway's own config.
    @app.get(f"{API}/config/schema", dependencies=[roles.viewer],
             responses={code: {"model": ErrorOut} for code in (401, 413)},
             summary="the config's JSON Schema: every key, its type, default and rule",
             tags=["config"])
    async def get_schema() -> dict[str, Any]:
        return config_schema()

    @app.get("/setup", response_class=HTMLResponse, include_in_schema=False)
    async def page() -> HTMLResponse:
        return HTMLResponse((resources.files("imu_gateway") / "static" / "setup.html")
                            .read_text(encoding="utf-8"))

    @app.put(f"{API}/config", dependencies=[roles.admin], responses=responses,
             summary="a new config (YAML or JSON): checked, applied live, saved",
             tags=["config"])
    async def put_config(
        request: Request,
        dry_run: Annotated[bool, Query(description="only check it and show the diff")] = False,
    ) -> JSONResponse:
        reloader = _reloader(gateway)
        text = await _body(request)
        try:
            data = parse_text(text, "the body")
            outcome = await reloader.put(data, dry_run)
        except ConfigError as exc:
            return JSONResponse({"error": f"the config has {len(exc.problems)} problem"
                                 f"{'s' if len(exc.problems) != 1 else ''}; nothing changed",
                                 "kind": "invalid_config", "problems": exc.problems}, 422)
        # (a move of this server comes after its answer: ``PutOutcome.then``)
        return JSONResponse(outcome.to_json(), background=outcome.then and BackgroundTask(
            outcome.then))


async def _body(request: Request) -> str:
    """The body as text, at most ``MAX_CONFIG_BODY`` bytes (read after the access
    check: an unauthorised client's body is never read)."""
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_CONFIG_BODY:
            raise RequestFailed(ErrorKind.TOO_LARGE, f"the body is over {MAX_CONFIG_BODY} bytes")
    try:
        return body.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS,
                            f"the body is not UTF-8 (bad byte at offset {exc.start})") from None
