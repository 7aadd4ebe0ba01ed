"""The FastAPI app: every route, made from the cache, the gateway object and the
command catalogue."""

from __future__ import annotations

import base64
import hashlib
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from importlib import resources
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from prometheus_client import CollectorRegistry, ProcessCollector, generate_latest
from starlette.exceptions import HTTPException as StarletteHTTPException

from ... import __version__
from ...cache import Snapshot, Status, iso_time
from ...commands import CATALOGUE, CommandSpec, commands_for, unknown_command
from ...config import HttpConfig
from ...derived import reading_json
from ...errors import KINDS, ErrorKind, RequestFailed
from ...history import KEEP_S
from ...model import VALUE_GROUPS, Group
from ...normalise import member_name
from ...stats import SensorStats
from ..common import GatewayLike, peer_json
from .access import (
    PAGE_POLICY,
    Authority,
    BodyGuard,
    CountRequests,
    Role,
    Roles,
    SecurityHeaders,
    declared_role,
    error_response,
    json_error,
    peer_of,
    who_of,
)
from .captures import capture_routes
from .config_routes import config_routes
from .limits import API, MAX_STREAMS
from .login import login_routes
from .metrics import GatewayCollector
from .models import (
    AlarmOut,
    ApiIndexOut,
    BusOut,
    CommandOut,
    ErrorOut,
    GroupOut,
    HealthOut,
    HistoryOut,
    ReadingOut,
    SensorDetailOut,
    SensorOut,
    TransitionOut,
)
from .procedures import procedure_routes
from .scan_routes import scan_routes
from .streams import EventStream, StreamHub, stream_peer
from .traffic import traffic_routes

#: Each error status's body, for the OpenAPI document.
ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": ErrorOut} for code in (401, 403, 404, 409, 413, 422, 502, 503, 504)}


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: ERRORS[code] for code in codes}


@dataclass(frozen=True)
class _Routes:
    """What the route groups share: the gateway, each role's dependency, and the one
    way an unknown sensor is refused."""

    gateway: GatewayLike
    roles: Roles

    def sensor_or_404(self, name: str) -> Snapshot:
        """(The cache refuses a sensor it does not know: ``unknown_sensor``, 404.)"""
        return self.gateway.cache.snapshot(name)


def create_app(gateway: GatewayLike, config: HttpConfig, hub: StreamHub | None = None,
               counters: dict[str, int] | None = None) -> FastAPI:
    """The FastAPI app.  ``hub`` and ``counters`` belong to the running server; without
    them (as for the OpenAPI document) the stream has a hub of its own."""
    app = FastAPI(
        title="imu-gateway",
        version=__version__,
        description="Readings, commands, live streams and metrics of IMU/VG/AH/MINS "
                    "attitude sensors behind one gateway.",
        docs_url=None,  # Swagger UI loads from a CDN: not on a plant network
        redoc_url=None,
    )
    _error_handlers(app)
    authority = Authority(config)
    routes = _Routes(gateway, Roles.of(authority))
    app.state.roles = routes.roles  # (for routes added beside these: roles.admin …)
    app.state.authority = authority  # (a reload gives it new credentials)
    login_routes(app, authority, routes.roles)
    _status_routes(app, routes)
    _sensor_routes(app, routes)
    _stream_routes(app, routes, hub if hub is not None else StreamHub(gateway))
    _alarm_routes(app, routes)
    for spec in CATALOGUE.values():
        _command_route(app, routes, spec)
    capture_routes(app, gateway, routes.roles)
    config_routes(app, gateway, routes.roles)
    procedure_routes(app, gateway, routes.roles)
    traffic_routes(app, gateway, routes.roles)
    scan_routes(app, gateway, routes.roles)
    _metrics_route(app, routes)
    app.add_middleware(BodyGuard, authority=authority)
    app.openapi = _openapi_of(app)  # type: ignore[method-assign]
    static = resources.files("imu_gateway") / "static"

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def dashboard() -> HTMLResponse:
        return HTMLResponse((static / "index.html").read_text(encoding="utf-8"))

    app.mount("/static", StaticFiles(packages=[("imu_gateway", "static")]), name="static")
    docs_policy = _docs_routes(app, routes.roles)
    app.add_middleware(SecurityHeaders, pages={"/": PAGE_POLICY, "/docs": docs_policy,
                                               "/wizards": PAGE_POLICY, "/setup": PAGE_POLICY,
                                               "/traffic": PAGE_POLICY})
    counts = counters if counters is not None else {"requests": 0}
    # outermost: counts every request, and brings the cache up to date before it
    app.add_middleware(CountRequests, counts=counts, before=gateway.cache.catch_up)
    return app


#: Where /docs loads Swagger UI's script and style from: this server (fastapi-offline
#: ships them in its wheel), never a CDN a plant network cannot reach.
DOCS_ASSETS = "/docs/assets"


def _docs_routes(app: FastAPI, roles: Roles) -> str:
    """The interactive API reference at ``/docs``, and ``/api/v1`` listing the
    endpoints (a client that starts at the API's root finds its way).  The docs
    page's Content-Security-Policy: the page policy, and its one inline script (which
    starts Swagger UI) by its hash."""
    app.mount(DOCS_ASSETS, StaticFiles(packages=[("fastapi_offline", "static")]),
              name="docs-assets")
    page = bytes(get_swagger_ui_html(
        openapi_url=app.openapi_url or "/openapi.json", title="imu-gateway API",
        swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
        swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
        swagger_favicon_url=f"{DOCS_ASSETS}/favicon.png").body)
    hashes = " ".join(f"'sha256-{base64.b64encode(hashlib.sha256(script).digest()).decode()}'"
                      for script in re.findall(rb"<script>(.*?)</script>", page, re.S))

    @app.get("/docs", response_class=HTMLResponse, include_in_schema=False)
    async def docs() -> HTMLResponse:
        return HTMLResponse(page)

    @app.get(API, response_model=ApiIndexOut, dependencies=[roles.public],
             summary="the endpoints of this API")
    async def index() -> dict[str, Any]:
        endpoints = [{"method": method, "path": route.path, "summary": route.summary or ""}
                     for route in app.routes if isinstance(route, APIRoute)
                     and route.include_in_schema and route.path.startswith(API)
                     for method in sorted(route.methods or ())]
        return {"name": "imu-gateway", "version": __version__, "docs": "/docs",
                "openapi": app.openapi_url, "endpoints": endpoints}

    return f"{PAGE_POLICY}; script-src 'self' {hashes}"


def _error_handlers(app: FastAPI) -> None:
    """Every error answers ``{"error", "kind"}`` (``access.error_response``)."""

    @app.exception_handler(RequestFailed)
    async def _failed(request: Request, exc: RequestFailed) -> JSONResponse:
        return error_response(exc)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        parts = []
        for err in exc.errors():
            where = ".".join(str(p) for p in err["loc"] if p != "body") or "body"
            parts.append(f"{where}: {err['msg'].removeprefix('Value error, ')}")
        return error_response(RequestFailed(ErrorKind.BAD_ARGUMENTS, "; ".join(parts)))

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code == 400:  # a body that is not even text: bad arguments too
            return error_response(RequestFailed(ErrorKind.BAD_ARGUMENTS, str(exc.detail)))
        kind = {404: ErrorKind.NOT_FOUND, 405: ErrorKind.METHOD_NOT_ALLOWED}.get(exc.status_code)
        response = json_error(exc.status_code, kind.value if kind else "http", str(exc.detail))
        response.headers.update(exc.headers or {})  # 405's Allow
        if exc.status_code == 405:  # every route of the path's (Starlette names one's)
            response.headers["Allow"] = ", ".join(sorted({
                method for route in request.app.routes if isinstance(route, APIRoute)
                and route.path_regex.match(request.url.path) for method in route.methods or ()}))
        return response


def _status_routes(app: FastAPI, routes: _Routes) -> None:
    """The gateway as a whole: health, buses, value groups."""
    gateway = routes.gateway

    @app.get(f"{API}/groups", response_model=list[GroupOut], dependencies=[routes.roles.viewer],
             responses=_errors(401), summary="the value groups and their units")
    async def groups() -> list[dict[str, Any]]:
        return [{"group": group.value, "fields": list(spec.fields),
                 "members": [member_name(group, f) for f in spec.fields],
                 "unit": spec.symbol, "unit_name": spec.name, "digits": spec.digits,
                 "derived_from": [g.value for g in Group if g in spec.derived_from]}
                for group, spec in VALUE_GROUPS.items()]

    @app.get(f"{API}/health", response_model=HealthOut, dependencies=[routes.roles.viewer],
             responses=_errors(401), summary="gateway and bus status")
    async def health() -> dict[str, Any]:
        buses = {b.name: b.port_open for b in gateway.stats()}
        counted = {s.value: 0 for s in Status}
        for snap in gateway.cache.snapshots():
            counted[snap.status.value] += 1
        degraded = not all(buses.values()) or counted["offline"] > 0
        return {"status": "degraded" if degraded else "ok",
                "gateway_id": gateway.config.gateway_id, "version": __version__,
                "uptime_s": round(time.monotonic() - gateway.started, 1),
                "buses": buses, "sensors": counted, "interfaces": gateway.config.interfaces(),
                "capture": gateway.captures is not None, "frontends": gateway.frontend_stats()}

    @app.get(f"{API}/buses", response_model=list[BusOut], dependencies=[routes.roles.viewer],
             responses=_errors(401), summary="every bus and its stats")
    async def buses() -> list[dict[str, Any]]:
        names = {b.name: [s.name for s in b.sensors] for b in gateway.config.buses}

        def timing(name: str) -> dict[str, Any]:
            stats = gateway.sensor_stats(name)
            return {"latency_ms": stats.latency_ms, "latency_dev_ms": stats.latency_dev_ms,
                    "timeout_ms": stats.timeout_ms, "late_answers": stats.late_answers,
                    "early_answers": stats.early_answers,
                    "requested_hz": stats.requested_hz, "achieved_hz": stats.achieved_hz}

        return [{**{k: v for k, v in b.as_dict().items() if k in BusOut.model_fields},
                 "sensors": names[b.name], "timing": {n: timing(n) for n in names[b.name]}}
                for b in gateway.stats()]


def _sensor_routes(app: FastAPI, routes: _Routes) -> None:
    """The sensors: the list, one sensor, its latest reading."""
    gateway = routes.gateway
    bodies: dict[str, tuple[tuple[int, Status], bytes]] = {}  # the latest reading's JSON

    def sensor_out(snap: Snapshot, stats: SensorStats) -> dict[str, Any]:
        sensor = gateway.sensors[snap.name]  # (a reload may change them: looked up here)
        bus = next(b for b, s in gateway.config.iter_sensors() if s.name == snap.name)
        return {"name": snap.name, "bus": bus.name, "series": sensor.series.name,
                "protocol": bus.protocol.name.lower(),
                "address": stats.address,  # the live one, after a set_address too
                "unit_id": sensor.unit_id, "status": snap.status.value, "online": snap.online,
                "busy": snap.busy, "streaming": snap.streaming, "seq": snap.seq,
                "ts": iso_time(snap.timestamp),
                "age_ms": None if snap.age_ms is None else round(snap.age_ms, 1),
                "achieved_hz": stats.achieved_hz, "requested_hz": stats.requested_hz,
                "errors": snap.errors,
                "commands": sorted(commands_for(sensor.series, bus.protocol),
                                   key=list(CATALOGUE).index)}

    @app.get(f"{API}/sensors", response_model=list[SensorOut], dependencies=[routes.roles.viewer],
             responses=_errors(401), summary="every sensor with its status")
    async def sensors() -> list[dict[str, Any]]:
        return [sensor_out(snap, gateway.sensor_stats(snap.name))
                for snap in gateway.cache.snapshots()]

    # exclude_unset: the reading's groups a series does not measure stay absent (as in
    # the reading JSON itself), while the nulls the route sets (age_ms …) stay null.
    @app.get(f"{API}/sensors/{{name}}", response_model=SensorDetailOut,
             response_model_exclude_unset=True, dependencies=[routes.roles.viewer],
             responses=_errors(401, 404), summary="a sensor's config, status and latest reading")
    async def sensor(name: str) -> dict[str, Any]:
        snap = routes.sensor_or_404(name)
        stats = gateway.sensor_stats(name)
        return {**sensor_out(snap, stats),
                "config": gateway.sensors[name].model_dump(mode="json"),
                "settings": gateway.cache.settings(name).to_json(),
                "stats": stats.as_dict(),
                "reading": snap.to_json() if snap.has_reading else None}

    @app.get(f"{API}/sensors/{{name}}/reading", response_model=ReadingOut,
             response_model_exclude_none=True, dependencies=[routes.roles.viewer],
             responses=_errors(401, 404, 409, 503, 504),
             summary="the latest reading; older than max_age_ms: a fresh bus read first")
    async def reading(name: str, max_age_ms: Annotated[float | None, Query(
            ge=0, le=3_600_000, description="the oldest reading acceptable, ms")] = None,
                      ) -> Response:
        snap = routes.sensor_or_404(name)
        if max_age_ms is not None:  # (a RequestFailed answers with its kind's status)
            snap = await gateway.read(name, max_age_ms)
        if not snap.has_reading:
            raise RequestFailed(ErrorKind.NO_READING, f"{name} has not been read yet")
        # The hot path: serialised once per sample and status however many clients
        # ask, and not validated against ReadingOut again (which only documents it).
        key = (snap.seq, snap.status)
        cached = bodies.get(name)
        if cached is None or cached[0] != key:
            cached = bodies[name] = (key, reading_json(snap))
        return Response(cached[1], media_type="application/json")


def _stream_routes(app: FastAPI, routes: _Routes, hub: StreamHub) -> None:
    """Server-Sent Events, of one sensor or of all."""

    def stream_response(sensor: str | None, request: Request) -> EventStream:
        if hub.open >= MAX_STREAMS:
            raise RequestFailed(ErrorKind.TOO_MANY_STREAMS, f"{MAX_STREAMS} streams are open")
        return EventStream(hub, sensor, stream_peer(request),
                           headers={"X-Accel-Buffering": "no"})  # (no-store: SecurityHeaders)

    sse = {"content": {"text/event-stream": {}},
           "description": "`event: reading` (or `status`) and `data:` the reading JSON; "
                          "`event: alarm` and `data:` the alarm's state after a transition "
                          "(as in `GET /api/v1/alarms`) with `from` and `by`; a "
                          "`: keep-alive` comment when idle"}

    @app.get(f"{API}/sensors/{{name}}/stream", dependencies=[routes.roles.viewer],
             response_class=StreamingResponse, responses={200: sse, **_errors(401, 404, 503)},
             summary="Server-Sent Events: one reading per event")
    async def stream(name: str, request: Request) -> EventStream:
        routes.sensor_or_404(name)
        return stream_response(name, request)

    @app.get(f"{API}/sensors/{{name}}/history", response_model=HistoryOut,
             dependencies=[routes.roles.viewer], responses=_errors(401, 404, 422),
             summary="the last minutes: per second, each field's lowest, highest and last")
    async def history(name: str, seconds: Annotated[float, Query(
            gt=0, le=KEEP_S, description=f"how far back, at most {KEEP_S} s")] = KEEP_S,
                      ) -> dict[str, Any]:
        routes.sensor_or_404(name)
        return hub.history.query(name, seconds, time.time())

    @app.get(f"{API}/stream", dependencies=[routes.roles.viewer], response_class=StreamingResponse,
             responses={200: sse, **_errors(401, 503)},
             summary="Server-Sent Events of every sensor")
    async def stream_all(request: Request) -> EventStream:
        return stream_response(None, request)


def _alarm_routes(app: FastAPI, routes: _Routes) -> None:
    """The alarms (docs/alarms.md): their states, the journal, acknowledgement."""
    gateway = routes.gateway

    @app.get(f"{API}/alarms", response_model=list[AlarmOut], dependencies=[routes.roles.viewer],
             responses=_errors(401), tags=["alarms"],
             summary="every alarm with its state (each sensor's communication alarm last)")
    async def alarms() -> list[dict[str, Any]]:
        return [state.to_json() for state in gateway.alarm_states()]

    @app.get(f"{API}/alarms/journal", response_model=list[TransitionOut],
             dependencies=[routes.roles.viewer], responses=_errors(401, 422), tags=["alarms"],
             summary="the alarms' transitions, oldest first (the last 1000)")
    async def journal(since: Annotated[float | datetime | None, Query(
            description="only those at or after this time: epoch seconds, or ISO 8601 "
                        "(`2026-11-22T03:40:00Z`; without a zone: UTC)")] = None,
                      ) -> list[dict[str, Any]]:
        wall = since if not isinstance(since, datetime) else (
            since.timestamp() if since.tzinfo else since.replace(tzinfo=UTC).timestamp())
        return [change.to_json() for change in gateway.alarm_journal(wall)]

    @app.post(f"{API}/alarms/{{sensor}}/{{alarm}}/ack", response_model=AlarmOut,
              dependencies=[routes.roles.operator], responses=_errors(401, 403, 404, 409),
              tags=["alarms"], summary="acknowledge an alarm (an operator's); its state "
                                       "after")
    async def acknowledge(sensor: str, alarm: str, request: Request, by: Annotated[
            str | None, Query(min_length=1, max_length=64, pattern=r"^[^\x00-\x1f\x7f]+$",
                              description="who acknowledges, for the journal")] = None,
                          ) -> dict[str, Any]:
        who = f"rest {peer_of(request)}, {who_of(request).name}"
        return gateway.acknowledge(sensor, alarm, f"{by} ({who})" if by else who).to_json()


def _metrics_route(app: FastAPI, routes: _Routes) -> None:
    """Prometheus's scrape, and the catch-all for commands nobody knows."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(GatewayCollector(routes.gateway))
    ProcessCollector(registry=registry)  # process_*: CPU, memory, open files

    @app.post(f"{API}/sensors/{{name}}/commands/{{command}}", include_in_schema=False,
              dependencies=[routes.roles.commands])
    async def other_command(name: str, command: str) -> None:
        routes.sensor_or_404(name)
        raise unknown_command(command)

    @app.get("/metrics", response_class=Response, dependencies=[routes.roles.viewer],
             responses={200: {"content": {"text/plain": {}}}, **_errors(401)},
             summary="Prometheus text format")
    async def metrics() -> Response:
        return Response(generate_latest(registry),
                        media_type="text/plain; version=0.0.4; charset=utf-8")


def _openapi_of(app: FastAPI) -> Callable[[], dict[str, Any]]:
    def openapi() -> dict[str, Any]:
        """FastAPI's document, with two additions and one correction: each operation's
        role (``x-role``: what its dependency declares); a viewer's bearer token is
        optional (required only with ``http.read_token_required``), which OpenAPI says
        with an empty alternative, and a public route takes none; and the command
        bodies' models."""
        if app.openapi_schema is None:
            document = get_openapi(title=app.title, version=app.version,
                                   description=app.description, routes=app.routes)
            for route in app.routes:
                role = declared_role(route) if isinstance(route, APIRoute) else None
                for method in getattr(route, "methods", None) or ():
                    operation = document["paths"].get(getattr(route, "path", ""), {}).get(
                        method.lower())
                    if operation is None or role is None:
                        continue
                    operation["x-role"] = role.label
                    if role is Role.PUBLIC:
                        operation.pop("security", None)
                    elif role is Role.VIEWER and "security" in operation:
                        operation["security"] = [{}, *operation["security"]]
            schemas = document.setdefault("components", {}).setdefault("schemas", {})
            for spec in CATALOGUE.values():  # the command bodies (``_command_route``)
                schemas[spec.args.__name__] = spec.args.model_json_schema(
                    ref_template="#/components/schemas/{model}")
            app.openapi_schema = document
        return app.openapi_schema

    return openapi


async def command_arguments(request: Request) -> Any:
    """A command's arguments: its JSON body (no body: none).  The catalogue checks them
    (``Gateway.command``), as it checks MQTT's and Modbus TCP's, so every front end
    refuses the same mistakes in the same words."""
    raw = await request.body()
    if not raw.strip():
        return None
    media = request.headers.get("content-type", "application/json").split(";")[0]
    media = media.strip().lower()
    if media != "application/json" and not media.endswith("+json"):
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS,
                            f"body: {media} is not JSON (send Content-Type: application/json)")
    try:
        return peer_json(raw)
    except (ValueError, RecursionError) as exc:  # bad UTF-8 is a ValueError too
        reason = str(exc) if isinstance(exc, ValueError) else "nested too deep"
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, f"body: not JSON ({reason})") from None


def _command_route(app: FastAPI, routes: _Routes, spec: CommandSpec) -> None:
    """``POST …/commands/{command}``, its body the command's own argument model (a
    command without arguments takes no body, or an empty object).  The OpenAPI
    document names that model (``_openapi_of`` adds it to the components)."""

    async def endpoint(name: str,
                       args: Annotated[Any, Depends(command_arguments)]) -> JSONResponse:
        routes.sensor_or_404(name)
        result = await routes.gateway.command(name, spec.name, args)
        status = 200 if result.ok else KINDS[result.kind or ErrorKind.FAILURE].status
        return JSONResponse(result.to_json(), status)

    schema: dict[str, Any] = {"$ref": f"#/components/schemas/{spec.args.__name__}"}
    if not spec.args.model_fields:  # no arguments: no body, ``{}`` or ``null``
        schema = {"anyOf": [schema, {"type": "null"}], "title": "Body"}
    app.add_api_route(
        f"{API}/sensors/{{name}}/commands/{spec.name}", endpoint, methods=["POST"],
        response_model=CommandOut, summary=spec.summary, name=f"command_{spec.name}",
        dependencies=[routes.roles.commands], tags=["commands"],
        responses=_errors(401, 403, 404, 409, 413, 422, 502, 504),
        openapi_extra={"requestBody": {"required": bool(spec.args.model_fields),
                                       "content": {"application/json": {"schema": schema}}}})


def openapi_document(gateway: GatewayLike, config: HttpConfig) -> dict[str, Any]:
    return create_app(gateway, config).openapi()
