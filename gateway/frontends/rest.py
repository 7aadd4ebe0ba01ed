"""The REST API, the live stream, the metrics and the dashboard (docs/rest.md).

FastAPI on uvicorn, inside the gateway's own event loop: the gateway owns the signals
and the shutdown (uvicorn would install handlers of its own; ``_Server`` stops it).
Every read is answered from the cache; ``max_age_ms`` is the one way a client can
cause bus traffic, and identical on-demand reads share one transaction.

Errors are one JSON shape, ``{"error": "...", "kind": "..."}``, with the status codes
docs/rest.md lists: 401/403 auth, 404 unknown sensor or command, 408 a request that
did not come in time, 409 busy, 422 bad arguments or a command the series lacks, 503
no reading yet, 504 the sensor did not answer; 502 when the sensor answered that the
command failed.

A client cannot hold the server: a connection is closed when a request's headers or
body are late, or when it stays idle (``_GuardedProtocol``), and a stream client is
dropped when its own socket stays full, never because the gateway is behind
(``StreamHub``).

The command routes are made from the command catalogue, so the OpenAPI document shows
each command's own arguments.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import inspect
import logging
import socket
import time
import typing
from collections import deque
from collections.abc import AsyncGenerator, Awaitable, Callable
from importlib import resources
from typing import Annotated, Any, ClassVar, Literal

import uvicorn
from fastapi import Depends, FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.staticfiles import StaticFiles
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from .. import __version__
from ..cache import EventKind, Snapshot, Status
from ..commands import CATALOGUE
from ..config import HttpConfig
from ..errors import KINDS, ErrorKind, RequestFailed
from ..model import GROUP_UNITS, Group
from ..normalise import GROUP_FIELDS
from ..stats import SensorStats
from ..supervise import Frontend, RepeatFilter
from .common import GatewayLike, json_bytes

log = logging.getLogger("gateway.http")

API = "/api/v1"
STREAM_QUEUE = 64  # events queued per stream client; past it, the oldest are skipped
STALL_S = 5.0  # a stream client whose socket has been full this long (queue full): dropped
KEEPALIVE_S = 15.0  # a comment line on an idle stream, so proxies keep it open
MAX_STREAMS = 1000
SEND_BUFFER = 64 * 1024  # bytes of kernel send buffer per connection
MAX_BODY = 16 * 1024  # a command's arguments are a few bytes
HEADER_DEADLINE_S = 10.0  # a request's headers, from connecting or from the previous answer
BODY_DEADLINE_S = 10.0  # a request's body, from the end of its headers
IDLE_S = 5  # a connection with no request under way (uvicorn's timeout_keep_alive)



# Module level: FastAPI resolves the (string) annotations of endpoints here.
_bearer = HTTPBearer(auto_error=False, description="the gateway's http.token")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


# ------------------------------------------------------------------ response models


class _Out(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ErrorOut(BaseModel):
    """Every error: what went wrong and its kind.  A command's failure also carries the
    command result's other fields (``ok``, ``sensor``, ``command``, ``answer``)."""

    model_config = ConfigDict(extra="allow")
    error: str
    kind: str


class AnglesOut(_Out):
    # None: the sensor sent something that is not a number (a Modbus float can be NaN)
    pitch: float | None
    roll: float | None
    yaw: float | None


class VectorOut(_Out):
    x: float | None
    y: float | None
    z: float | None


class QuaternionOut(_Out):
    q0: float | None
    q1: float | None
    q2: float | None
    q3: float | None


_GROUPS = ("angles", "accel", "gyro", "mag", "quaternion")


def _groups_never_null(schema: dict[str, Any]) -> None:
    """A value group is absent when not measured, never null: say so in the schema
    (the Python type keeps ``None`` as the default for "absent", which is never sent)."""
    for name in _GROUPS:
        prop = schema["properties"][name]
        prop.pop("default", None)
        choices = prop.pop("anyOf")
        prop.update(next(c for c in choices if c.get("type") != "null"))


class ReadingOut(_Out):
    """The reading JSON (as on MQTT); groups the series does not measure are absent."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_groups_never_null)
    sensor: str
    ts: str | None = Field(description="when the sample arrived, UTC")
    seq: int
    status: Literal["ok", "stale", "offline"]
    angles: AnglesOut | None = Field(None, description=GROUP_UNITS[Group.ANGLES].name)
    accel: VectorOut | None = Field(None, description=GROUP_UNITS[Group.ACCEL].name)
    gyro: VectorOut | None = Field(None, description=GROUP_UNITS[Group.GYRO].name)
    mag: VectorOut | None = Field(None, description=GROUP_UNITS[Group.MAG].name)
    quaternion: QuaternionOut | None = Field(
        None, description=GROUP_UNITS[Group.QUATERNION].name)


class GroupOut(_Out):
    """A value group of the reading JSON: its fields and how its values are told."""

    group: str = Field(description="the group's key in the reading JSON")
    fields: list[str] = Field(description="its fields, as in per-field topics and registers")
    unit: str = Field(description="the unit's symbol (empty: none)")
    unit_name: str = Field(description="the unit in words")
    digits: int = Field(description="decimals of the sensors' resolution")


class SensorOut(_Out):
    name: str
    bus: str
    series: str
    protocol: str
    address: int
    unit_id: int
    status: Literal["ok", "stale", "offline"]
    online: bool
    busy: bool
    streaming: bool
    seq: int
    age_ms: float | None
    achieved_hz: float
    errors: int


class SensorDetailOut(SensorOut):
    config: dict[str, Any]
    settings: dict[str, Any] = Field(description=(
        "what the gateway learnt from commands (and Modbus pass-through); busy_with only "
        "while a save or calibration runs"))
    stats: dict[str, Any]
    reading: ReadingOut | None


class TimingOut(_Out):
    latency_ms: float | None = Field(description="smoothed answer latency: the sensor's "
                                     "turnaround plus the adapter's; null before an answer")
    latency_dev_ms: float | None = Field(description="its mean deviation")
    timeout_ms: float = Field(description="what the next attempt waits beyond the wire time")
    late_answers: int
    requested_hz: float = Field(description="the configured rate: stream_hz while it "
                                "streams, else poll_hz (0: polled flat out)")
    achieved_hz: float = Field(description="readings a second, lately")


class BusOut(_Out):
    name: str
    port: str
    baudrate: int
    protocol: str
    port_open: bool
    transactions: int
    errors: dict[str, int]
    transactions_per_s: float
    utilisation: float = Field(description="time in exchanges ÷ elapsed time")
    wire_utilisation: float
    busy_ms: int
    queue_depth: int
    late_answers: int = Field(description="answers that came after their timeout, and "
                              "were used")
    sensors: list[str]
    timing: dict[str, TimingOut] = Field(description="each sensor's learned answer timing")


class HealthOut(_Out):
    status: Literal["ok", "degraded"] = Field(
        description="degraded: a port is closed or a sensor is offline")
    gateway_id: str
    version: str
    uptime_s: float
    buses: dict[str, bool] = Field(description="bus name -> port open")
    sensors: dict[str, int] = Field(description="how many sensors are ok, stale, offline")
    interfaces: list[str]
    frontends: dict[str, dict[str, float]] = Field(description=(
        "front end -> its counters: clients, requests, restarts (after a failure) and "
        "those of docs/reliability.md"))


class CommandOut(_Out):
    ok: bool
    sensor: str
    command: str
    answer: dict[str, Any]
    error: str | None
    kind: str | None


# ------------------------------------------------------------------ the live stream


class StreamPeer(typing.Protocol):
    """A stream client's connection, as the hub judges it (``_GuardedProtocol``)."""

    @property
    def write_stalled(self) -> bool:
        """The client's socket has been full, nothing taken from it, for ``STALL_S``."""

    def abort(self) -> None: ...


class _Subscriber:
    def __init__(self, sensor: str | None, peer: StreamPeer | None) -> None:
        self.sensor = sensor
        self.peer = peer  # None: no socket to judge by (the hub used on its own)
        self.events: deque[bytes] = deque()
        self.wake = asyncio.Event()
        self.dropped = False


class StreamHub:
    """Server-Sent Events: every reading (and status change) to every subscriber of
    its sensor.  An event is formatted once, whatever the number of subscribers.

    At most ``STREAM_QUEUE`` events wait per subscriber.  When one more comes, the
    subscriber is judged by its own socket, never by how far behind its queue is (the
    queue also fills while the gateway's loop is behind, its client reading well):

    - its client has taken nothing for ``STALL_S`` (the socket stayed full): dropped,
      its connection closed, rather than the gateway buffering without bound;
    - otherwise its oldest event is skipped (and counted): the client stays, and
      catches up with the newest readings."""

    def __init__(self, gateway: GatewayLike,
                 on_error: Callable[[BaseException], None] | None = None) -> None:
        self.gateway = gateway
        self.subscribers: set[_Subscriber] = set()  # those events go to
        # Streams not yet ended, dropped ones included (until their connection has
        # closed): they count against MAX_STREAMS.
        self.open = 0
        self.dropped = 0  # subscribers dropped as stalled
        self.skipped = 0  # events skipped for subscribers whose queue was full
        self.closing = asyncio.Event()
        self._unsubscribe = gateway.cache.subscribe(self._on_cache_event, on_error)

    def _on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if not self.subscribers:
            return
        event = _event("reading" if kind is EventKind.READING else "status", snap)
        for sub in list(self.subscribers):
            if sub.sensor is not None and sub.sensor != snap.name:
                continue
            if len(sub.events) >= STREAM_QUEUE:
                if sub.peer is not None and sub.peer.write_stalled:
                    self._drop(sub)
                    continue
                sub.events.popleft()
                self.skipped += 1
            sub.events.append(event)
            sub.wake.set()

    def _drop(self, sub: _Subscriber) -> None:
        sub.dropped = True
        sub.events.clear()
        self.subscribers.discard(sub)
        self.dropped += 1
        log.info("http: dropped a stream client that took nothing for %g s", STALL_S)
        # Its send waits on a full socket, so the stream could only end once the client
        # read again (a zero window is kept open for ever): the connection goes now.
        assert sub.peer is not None
        sub.peer.abort()
        sub.wake.set()

    async def stream(self, sensor: str | None,
                     peer: StreamPeer | None = None) -> AsyncGenerator[bytes, None]:
        sub = _Subscriber(sensor, peer)
        self.subscribers.add(sub)
        self.open += 1
        try:
            names = [sensor] if sensor is not None else self.gateway.cache.names
            for name in names:  # where each sensor stands now, first
                snap = self.gateway.cache.snapshot(name)
                yield _event("reading" if snap.has_reading else "status", snap)
            while not self.closing.is_set() and not sub.dropped:
                if not sub.events:
                    sub.wake.clear()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(sub.wake.wait(), KEEPALIVE_S)
                    if not sub.events:
                        yield b": keep-alive\n\n"
                        continue
                yield sub.events.popleft()
        finally:
            self.subscribers.discard(sub)
            self.open -= 1

    def close(self) -> None:
        self.closing.set()
        for sub in self.subscribers:
            sub.wake.set()
        self._unsubscribe()


def _event(name: str, snap: Snapshot) -> bytes:
    return b"event: %s\nid: %d\ndata: %s\n\n" % (name.encode(), snap.seq,
                                                json_bytes(snap.to_json()))


class _CommandGuard:
    """ASGI middleware in front of the command routes.  FastAPI reads and parses a
    body before it runs the route's dependencies, so without this an unauthorised
    client could make the gateway read a body of any size.  Here the access rules
    come first, then at most ``MAX_BODY`` bytes are read (413 beyond), and the body
    is handed on as it came."""

    def __init__(self, app: Any, config: HttpConfig) -> None:
        self.app, self.config = app, config

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope["method"] not in ("POST", "PUT", "PATCH"):
            await self.app(scope, receive, send)
            return
        refusal = self._refusal(scope)
        if refusal is not None:
            await error_response(refusal)(scope, receive, send)
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

    def _refusal(self, scope: Any) -> RequestFailed | None:
        if not scope["path"].startswith(f"{API}/sensors/") or "/commands/" not in scope["path"]:
            return None
        headers = dict(scope["headers"])
        scheme, _, token = headers.get(b"authorization", b"").decode("latin-1").partition(" ")
        return command_refusal(self.config, token if scheme.lower() == "bearer" else None)


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


def error_response(exc: RequestFailed) -> JSONResponse:
    """Every failed request's answer: ``{"error", "kind"}`` with the kind's status
    (``gateway.errors.KINDS``), and the challenge with a 401."""
    return json_error(exc.status, exc.kind.value, str(exc))


def json_error(status: int, kind: str, message: str) -> JSONResponse:
    """An error answer of any status, the HTTP layer's own (404 of a path, 405) too."""
    headers = {"WWW-Authenticate": "Bearer"} if status == 401 else None
    return JSONResponse({"error": message, "kind": kind}, status, headers)


class _CountRequests:
    """ASGI middleware counting HTTP requests (a plain one: Starlette's
    ``BaseHTTPMiddleware`` costs a task and a stream per request)."""

    def __init__(self, app: Any, counts: dict[str, int]) -> None:
        self.app, self.counts = app, counts

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] == "http":
            self.counts["requests"] += 1
        await self.app(scope, receive, send)


# ------------------------------------------------------------------ metrics


HTTP_COUNTERS = (  # the HTTP server's own: metric, its key in HttpServer.stats(), help
    ("http_request_timeouts", "request_timeouts",
     "connections closed: a request's headers or body did not come in time"),
    ("http_streams_dropped", "dropped_streams", "stream clients dropped: their socket "
     "stayed full"),
    ("http_stream_events_skipped", "skipped_events", "events skipped for stream clients "
     "behind, the oldest first"),
)


class GatewayCollector:
    """Prometheus metrics, read from the gateway's stats at each scrape."""

    def __init__(self, gateway: GatewayLike) -> None:
        self.gateway = gateway

    def collect(self) -> list[Metric]:
        g = self.gateway
        p = "imu_gateway_"
        out: list[Metric] = []

        def family(kind: type[GaugeMetricFamily] | type[CounterMetricFamily], name: str,
                   doc: str, labels: list[str]) -> Any:
            metric = kind(p + name, doc, labels=labels)
            out.append(metric)
            return metric

        tx = family(CounterMetricFamily, "bus_transactions", "exchanges on the line", ["bus"])
        errors = family(CounterMetricFamily, "bus_errors", "failed exchanges by kind",
                        ["bus", "kind"])
        util = family(GaugeMetricFamily, "bus_utilisation",
                      "time in exchanges / elapsed time", ["bus"])
        queue = family(GaugeMetricFamily, "bus_queue_depth", "jobs waiting for the line",
                       ["bus"])
        port = family(GaugeMetricFamily, "bus_port_open", "1 when the port is open", ["bus"])
        for bus in g.stats():
            tx.add_metric([bus.name], bus.transactions)
            for kind, count in bus.errors.items():
                errors.add_metric([bus.name, kind], count)
            util.add_metric([bus.name], bus.utilisation)
            queue.add_metric([bus.name], bus.queue_depth)
            port.add_metric([bus.name], 1.0 if bus.port_open else 0.0)

        rate = family(GaugeMetricFamily, "sensor_rate_hz", "readings per second", ["sensor"])
        age = family(GaugeMetricFamily, "sensor_age_seconds", "age of the latest reading",
                     ["sensor"])
        status = family(GaugeMetricFamily, "sensor_status", "1 for the sensor's status",
                        ["sensor", "status"])
        readings = family(CounterMetricFamily, "sensor_readings", "readings received",
                          ["sensor"])
        sensor_errors = family(CounterMetricFamily, "sensor_errors", "timeouts and bad frames",
                               ["sensor"])
        latency = family(GaugeMetricFamily, "sensor_latency_seconds", "smoothed answer "
                         "latency (the sensor's turnaround plus the adapter's)", ["sensor"])
        timeout = family(GaugeMetricFamily, "sensor_timeout_seconds", "answer timeout beyond "
                         "the wire time, learned from the latency", ["sensor"])
        late = family(CounterMetricFamily, "sensor_late_answers", "answers after their "
                      "timeout, used", ["sensor"])
        stops = family(CounterMetricFamily, "sensor_stream_stops", "stops sent to a sensor "
                       "found streaming unasked", ["sensor"])
        for snap in g.cache.snapshots():
            stats = g.sensor_stats(snap.name)
            rate.add_metric([snap.name], stats.achieved_hz)
            if stats.latency_ms is not None:
                latency.add_metric([snap.name], stats.latency_ms / 1000)
            timeout.add_metric([snap.name], stats.timeout_ms / 1000)
            late.add_metric([snap.name], stats.late_answers)
            stops.add_metric([snap.name], stats.stream_stops)
            if snap.age_ms is not None:
                age.add_metric([snap.name], snap.age_ms / 1000)
            for s in Status:
                status.add_metric([snap.name, s.value], 1.0 if snap.status is s else 0.0)
            readings.add_metric([snap.name], snap.seq)
            sensor_errors.add_metric([snap.name], snap.errors)

        clients = family(GaugeMetricFamily, "frontend_clients", "connected clients",
                         ["frontend"])
        requests = family(CounterMetricFamily, "frontend_requests", "requests served",
                          ["frontend"])
        restarts = family(CounterMetricFamily, "frontend_restarts", "restarts after a "
                          "failure (docs/reliability.md)", ["frontend"])
        frontends = g.frontend_stats()
        for name, served in frontends.items():
            restarts.add_metric([name], served["restarts"])
            if "clients" in served:  # the servers (the MQTT client has its own below)
                clients.add_metric([name], served["clients"])
                requests.add_metric([name], served["requests"])
        for name, key, doc in HTTP_COUNTERS if "http" in frontends else ():
            family(CounterMetricFamily, name, doc, []).add_metric([], frontends["http"][key])
        mqtt = frontends.get("mqtt")
        if mqtt is not None:
            family(GaugeMetricFamily, "mqtt_connected", "1 when connected to the broker",
                   []).add_metric([], 1.0 if mqtt["connected"] else 0.0)
            family(CounterMetricFamily, "mqtt_published", "messages handed to the client",
                   []).add_metric([], mqtt["published"])
            family(CounterMetricFamily, "mqtt_dropped", "messages dropped while the broker "
                   "was away", []).add_metric([], mqtt["dropped"])
        return out


# ------------------------------------------------------------------ the app


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
    counts = counters if counters is not None else {"requests": 0}
    registry = CollectorRegistry(auto_describe=False)
    registry.register(GatewayCollector(gateway))
    errors: dict[int | str, dict[str, Any]] = {
        code: {"model": ErrorOut} for code in (401, 403, 404, 409, 413, 422, 502, 503, 504)}

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
        return response


    def authorised(credentials: HTTPAuthorizationCredentials | None) -> None:
        if credentials is None or not token_matches(credentials.credentials, config.token):
            raise RequestFailed(ErrorKind.UNAUTHORISED, "a valid bearer token is required")

    # async, like every dependency here: FastAPI runs a plain def in a worker thread,
    # a thread hop per request (measured: it halved the readings/s).
    async def read_access(credentials: Credentials) -> None:
        if config.read_token_required:
            authorised(credentials)

    async def command_access(credentials: Credentials) -> None:
        refusal = command_refusal(config, credentials.credentials if credentials else None)
        if refusal is not None:
            raise refusal

    reads = [Depends(read_access)]

    async def stream_access(credentials: Credentials, access_token: Annotated[
            str | None, Query(description="the token, for clients that cannot send "
                              "headers (a browser's EventSource; RFC 6750 §2.3)")] = None,
                            ) -> None:
        if config.read_token_required and not (
                access_token is not None and token_matches(access_token, config.token)):
            authorised(credentials)

    streams = [Depends(stream_access)]

    def sensor_or_404(name: str) -> Snapshot:
        if name not in gateway.sensors:
            raise RequestFailed(ErrorKind.UNKNOWN_SENSOR, f"unknown sensor {name!r}")
        return gateway.cache.snapshot(name)

    bus_of = {s.name: b for b, s in gateway.config.iter_sensors()}
    bodies: dict[str, tuple[tuple[int, Status], bytes]] = {}  # the latest reading's JSON

    def sensor_out(snap: Snapshot, stats: SensorStats) -> dict[str, Any]:
        sensor, bus = gateway.sensors[snap.name], bus_of[snap.name]
        return {"name": snap.name, "bus": bus.name, "series": sensor.series.name,
                "protocol": bus.protocol.name.lower(),
                "address": stats.address,  # the live one, after a set_address too
                "unit_id": sensor.unit_id, "status": snap.status.value, "online": snap.online,
                "busy": snap.busy, "streaming": snap.streaming, "seq": snap.seq,
                "age_ms": None if snap.age_ms is None else round(snap.age_ms, 1),
                "achieved_hz": stats.achieved_hz, "errors": snap.errors}

    @app.get(f"{API}/groups", response_model=list[GroupOut], dependencies=reads,
             responses={401: errors[401]}, summary="the value groups and their units")
    async def groups() -> list[dict[str, Any]]:
        return [{"group": group.value, "fields": list(fields), "unit": unit.symbol,
                 "unit_name": unit.name, "digits": unit.digits}
                for group, (_, fields) in GROUP_FIELDS.items()
                for unit in (GROUP_UNITS[group],)]

    @app.get(f"{API}/health", response_model=HealthOut, dependencies=reads,
             responses={401: errors[401]}, summary="gateway and bus status")
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
                "frontends": gateway.frontend_stats()}

    @app.get(f"{API}/buses", response_model=list[BusOut], dependencies=reads,
             responses={401: errors[401]}, summary="every bus and its stats")
    async def buses() -> list[dict[str, Any]]:
        names = {b.name: [s.name for s in b.sensors] for b in gateway.config.buses}

        def timing(name: str) -> dict[str, Any]:
            stats = gateway.sensor_stats(name)
            return {"latency_ms": stats.latency_ms, "latency_dev_ms": stats.latency_dev_ms,
                    "timeout_ms": stats.timeout_ms, "late_answers": stats.late_answers,
                    "requested_hz": stats.requested_hz, "achieved_hz": stats.achieved_hz}

        return [{**{k: v for k, v in b.as_dict().items() if k in BusOut.model_fields},
                 "sensors": names[b.name], "timing": {n: timing(n) for n in names[b.name]}}
                for b in gateway.stats()]

    @app.get(f"{API}/sensors", response_model=list[SensorOut], dependencies=reads,
             responses={401: errors[401]}, summary="every sensor with its status")
    async def sensors() -> list[dict[str, Any]]:
        return [sensor_out(snap, gateway.sensor_stats(snap.name))
                for snap in gateway.cache.snapshots()]

    # exclude_unset: the reading's groups a series does not measure stay absent (as in
    # the reading JSON itself), while the nulls the route sets (age_ms …) stay null.
    @app.get(f"{API}/sensors/{{name}}", response_model=SensorDetailOut,
             response_model_exclude_unset=True, dependencies=reads,
             responses={401: errors[401], 404: errors[404]},
             summary="a sensor's config, status and latest reading")
    async def sensor(name: str) -> dict[str, Any]:
        snap = sensor_or_404(name)
        stats = gateway.sensor_stats(name)
        return {**sensor_out(snap, stats),
                "config": gateway.sensors[name].model_dump(mode="json"),
                "settings": gateway.cache.settings(name),
                "stats": stats.as_dict(),
                "reading": snap.to_json() if snap.has_reading else None}

    @app.get(f"{API}/sensors/{{name}}/reading", response_model=ReadingOut,
             response_model_exclude_none=True, dependencies=reads,
             responses={code: errors[code] for code in (401, 404, 409, 503, 504)},
             summary="the latest reading; older than max_age_ms: a fresh bus read first")
    async def reading(name: str, max_age_ms: Annotated[float | None, Query(
            ge=0, le=3_600_000, description="the oldest reading acceptable, ms")] = None,
                      ) -> Response:
        snap = sensor_or_404(name)
        if max_age_ms is not None:  # (a RequestFailed answers with its kind's status)
            snap = await gateway.read(name, max_age_ms)
        if not snap.has_reading:
            raise RequestFailed(ErrorKind.NO_READING, f"{name} has not been read yet")
        # The hot path: serialised once per sample and status however many clients
        # ask, and not validated against ReadingOut again (which only documents it).
        key = (snap.seq, snap.status)
        cached = bodies.get(name)
        if cached is None or cached[0] != key:
            cached = bodies[name] = (key, json_bytes(snap.to_json()))
        return Response(cached[1], media_type="application/json")

    streams_hub = hub if hub is not None else StreamHub(gateway)

    def stream_response(sensor: str | None, request: Request) -> StreamingResponse:
        if streams_hub.open >= MAX_STREAMS:
            raise RequestFailed(ErrorKind.TOO_MANY_STREAMS, f"{MAX_STREAMS} streams are open")
        return StreamingResponse(streams_hub.stream(sensor, stream_peer(request)),
                                 media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache",
                                          "X-Accel-Buffering": "no"})

    sse = {"content": {"text/event-stream": {}},
           "description": "`event: reading` (or `status`), `id: seq`, `data:` the "
                          "reading JSON; a `: keep-alive` comment when idle"}

    @app.get(f"{API}/sensors/{{name}}/stream", dependencies=streams,
             response_class=StreamingResponse,
             responses={200: sse, 401: errors[401], 404: errors[404], 503: errors[503]},
             summary="Server-Sent Events: one reading per event")
    async def stream(name: str, request: Request) -> StreamingResponse:
        sensor_or_404(name)
        return stream_response(name, request)

    @app.get(f"{API}/stream", dependencies=streams, response_class=StreamingResponse,
             responses={200: sse, 401: errors[401], 503: errors[503]},
             summary="Server-Sent Events of every sensor")
    async def stream_all(request: Request) -> StreamingResponse:
        return stream_response(None, request)

    for spec in CATALOGUE.values():
        _command_route(app, gateway, spec.name, spec.args, spec.summary, command_access,
                       sensor_or_404, errors)

    @app.post(f"{API}/sensors/{{name}}/commands/{{command}}", include_in_schema=False)
    async def unknown_command(name: str, command: str) -> None:
        sensor_or_404(name)
        raise RequestFailed(ErrorKind.UNKNOWN_COMMAND,
                       f"unknown command {command!r} (known: {', '.join(CATALOGUE)})")

    @app.get("/metrics", response_class=Response, dependencies=reads,
             responses={200: {"content": {"text/plain": {}}}, 401: errors[401]},
             summary="Prometheus text format")
    async def metrics() -> Response:
        return Response(generate_latest(registry),
                        media_type="text/plain; version=0.0.4; charset=utf-8")

    app.add_middleware(_CommandGuard, config=config)
    app.add_middleware(_CountRequests, counts=counts)  # outermost: counts every request

    def openapi() -> dict[str, Any]:
        """FastAPI's document, with one correction: a read's bearer token is optional
        (required only with ``http.read_token_required``), which OpenAPI says with an
        empty alternative."""
        if app.openapi_schema is None:
            document = get_openapi(title=app.title, version=app.version,
                                   description=app.description, routes=app.routes)
            for path in document["paths"].values():
                operation = path.get("get")
                if operation is not None and "security" in operation:
                    operation["security"] = [{}, *operation["security"]]
            app.openapi_schema = document
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]

    static = resources.files("gateway") / "static"

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def dashboard() -> HTMLResponse:
        return HTMLResponse((static / "index.html").read_text(encoding="utf-8"))

    app.mount("/static", StaticFiles(packages=[("gateway", "static")]), name="static")
    return app


def _command_route(app: FastAPI, gateway: GatewayLike, command: str, args: type[BaseModel],
                   summary: str, access: Callable[..., Awaitable[None]],
                   sensor_or_404: Callable[[str], Snapshot],
                   errors: dict[int | str, dict[str, Any]]) -> None:
    """``POST …/commands/{command}``, its body the command's own argument model (a
    command without arguments takes no body, or an empty object)."""

    async def endpoint(name: str, body: BaseModel | None = None) -> JSONResponse:
        sensor_or_404(name)
        values = body.model_dump() if body is not None else {}
        result = await gateway.command(name, command, values)
        status = 200 if result.ok else KINDS[result.kind or ErrorKind.FAILURE].status
        return JSONResponse(result.to_json(), status)

    # The body's type is the command's model, known only here: FastAPI reads it from
    # the signature.
    body = inspect.Parameter(
        "body", inspect.Parameter.POSITIONAL_OR_KEYWORD,
        annotation=args if args.model_fields else args | None,
        **({} if args.model_fields else {"default": None}))
    endpoint.__signature__ = inspect.Signature(  # type: ignore[attr-defined]
        [inspect.Parameter("name", inspect.Parameter.POSITIONAL_OR_KEYWORD, annotation=str),
         body], return_annotation=JSONResponse)
    app.add_api_route(
        f"{API}/sensors/{{name}}/commands/{command}", endpoint, methods=["POST"],
        response_model=CommandOut, summary=summary, name=f"command_{command}",
        dependencies=[Depends(access)], tags=["commands"],
        responses={code: errors[code] for code in (401, 403, 404, 409, 413, 422, 502, 504)})


# ------------------------------------------------------------------ the server


PEER = "imu_gateway.peer"  # the ASGI scope extension that carries a request's connection


def stream_peer(request: Request) -> StreamPeer | None:
    """The connection a request came on, when ``_GuardedProtocol`` serves it."""
    peer = request.scope.get("extensions", {}).get(PEER, {}).get("connection")
    return peer if isinstance(peer, _GuardedProtocol) else None


def _cancel(timer: asyncio.TimerHandle | None) -> None:
    if timer is not None:
        timer.cancel()


class _GuardedProtocol(HttpToolsProtocol):
    """uvicorn's HTTP/1.1 protocol with the deadlines uvicorn lacks.  (httptools, named
    rather than uvicorn's "auto", so the behaviour does not depend on what is installed.)

    uvicorn waits for ever for a request's headers and body, so a client that sends
    part of a request, or nothing, holds its connection, and a few hundred such hold
    the connection cap (``limit_concurrency``).  Here:

    - a connection that sends nothing is closed after ``IDLE_S``, as a kept-alive one
      is (uvicorn arms that timer only after an answer);
    - a request's headers must be complete ``HEADER_DEADLINE_S`` after connecting, or
      after the previous answer on a kept-alive connection (a trickle of bytes does
      not extend it);
    - its body ``BODY_DEADLINE_S`` after its headers.

    A late request is answered 408 if no answer is under way, and its connection closed.

    For the stream hub, ``write_stalled`` says the client's socket has been full, with
    nothing taken from it, for ``STALL_S``."""

    counters: ClassVar[dict[str, int]] = {}  # the server's (``_protocol_for``)
    write_stalled = False
    _header_timer: asyncio.TimerHandle | None = None
    _body_timer: asyncio.TimerHandle | None = None
    _stall_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self.timeout_keep_alive_task = self.loop.call_later(
            self.timeout_keep_alive, self.timeout_keep_alive_handler)
        self._await_headers()

    def connection_lost(self, exc: Exception | None) -> None:
        for timer in (self._header_timer, self._body_timer, self._stall_timer):
            _cancel(timer)
        super().connection_lost(exc)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self.scope["extensions"] = {PEER: {"connection": self}}  # for stream_peer

    def on_headers_complete(self) -> None:
        _cancel(self._header_timer)
        super().on_headers_complete()
        # Disarmed by on_message_complete, which comes at once when there is no body.
        self._body_timer = self.loop.call_later(BODY_DEADLINE_S, self._late, "body",
                                                BODY_DEADLINE_S)

    def on_message_complete(self) -> None:
        _cancel(self._body_timer)
        super().on_message_complete()

    def on_response_complete(self) -> None:
        pipelined = bool(self.pipeline)  # a request whose headers are in starts now
        super().on_response_complete()
        if not pipelined and not self.transport.is_closing():
            self._await_headers()

    def _await_headers(self) -> None:
        _cancel(self._header_timer)
        self._header_timer = self.loop.call_later(HEADER_DEADLINE_S, self._late, "headers",
                                                  HEADER_DEADLINE_S)

    def _late(self, part: str, seconds: float) -> None:
        if self.transport.is_closing():
            return
        self.counters["request_timeouts"] += 1
        log.debug("http: %s: the request's %s did not come within %g s", self.client,
                  part, seconds)
        if self.cycle is None or self.cycle.response_complete or not self.cycle.response_started:
            body = json_bytes({"error": f"the request's {part} did not come within "
                                        f"{seconds:g} s", "kind": ErrorKind.REQUEST_TIMEOUT.value})
            head = [b"HTTP/1.1 408 Request Timeout\r\n",
                    *(b"%s: %s\r\n" % h for h in self.server_state.default_headers),
                    b"content-type: application/json\r\n",
                    b"content-length: %d\r\n" % len(body), b"connection: close\r\n\r\n"]
            self.transport.write(b"".join(head) + body)
        # close() waits until what is buffered is sent: for a client that does not
        # read, for ever.
        if self.transport.get_write_buffer_size():
            self.transport.abort()
        else:
            self.transport.close()

    # The client's socket: asyncio pauses writing when the bytes the kernel would not
    # take pass the high-water mark, and resumes once most are sent.
    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stall_timer is None:
            self._stall_timer = self.loop.call_later(STALL_S, self._stalled)

    def resume_writing(self) -> None:
        super().resume_writing()
        _cancel(self._stall_timer)
        self._stall_timer = None
        self.write_stalled = False

    def _stalled(self) -> None:
        # A timer rather than comparing clocks at the next event: a turn of the loop
        # runs the I/O callbacks before the due timers, so after the loop was merely
        # behind, the socket has been written to (and writing resumed) before this.
        self._stall_timer = None
        self.write_stalled = True

    def abort(self) -> None:
        self.transport.abort()


def _protocol_for(server_counters: dict[str, int]) -> type[_GuardedProtocol]:
    """The protocol class for one server, counting into its counters (uvicorn makes
    each connection's protocol itself, from the class)."""

    class Protocol(_GuardedProtocol):
        counters = server_counters

    return Protocol


class _Server(uvicorn.Server):
    """uvicorn without its signal handlers: the gateway owns SIGINT and SIGTERM."""

    @contextlib.contextmanager
    def capture_signals(self) -> Any:
        yield


class HttpServer(Frontend):
    name = "http"

    def __init__(self, gateway: GatewayLike, config: HttpConfig) -> None:
        super().__init__()
        self.gateway = gateway
        self.config = config
        self.counters = {"requests": 0, "request_timeouts": 0}
        self.hub: StreamHub | None = None
        self._socket: socket.socket | None = None
        self._server: _Server | None = None
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        """Listen; raises ``OSError`` when the address cannot be bound."""
        listen = self.config.listen
        family = socket.AF_INET6 if ":" in listen.host else socket.AF_INET
        # proto given: asyncio sets TCP_NODELAY only on sockets that say they are TCP,
        # and without it each keep-alive answer waits 40 ms for a delayed ACK.
        sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            # Accepted connections inherit this: the kernel's buffer for a client that
            # stops reading stays small (it may otherwise grow to megabytes), so a
            # stalled stream client is noticed, and dropped, within seconds.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
            sock.bind((listen.host, listen.port))
            sock.listen(512)
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        self._socket = sock
        self.hub = StreamHub(self.gateway, on_error=self.fail)
        uvicorn_log = logging.getLogger("uvicorn.error")
        if not any(isinstance(f, RepeatFilter) for f in uvicorn_log.filters):
            uvicorn_log.addFilter(RepeatFilter())  # it warns once per odd request
        app = create_app(self.gateway, self.config, self.hub, self.counters)
        self._server = _Server(uvicorn.Config(
            app, log_config=None, log_level="warning", access_log=False, lifespan="off",
            timeout_graceful_shutdown=2, server_header=False,
            http=_protocol_for(self.counters), ws="none", timeout_keep_alive=IDLE_S,
            # every connection and request at once, stalled ones included: 503 beyond
            limit_concurrency=MAX_STREAMS + 100))
        self._task = asyncio.create_task(self._server.serve(sockets=[sock]), name="http")
        self._task.add_done_callback(self._ended)
        log.info("HTTP on http://%s:%d/ (API %s)", listen.host, self.port, API)

    def _ended(self, task: asyncio.Task[None]) -> None:
        """uvicorn's server ends only when told to: otherwise it failed."""
        if task.cancelled() or (self._server is not None and self._server.should_exit):
            return
        self.fail(task.exception() or RuntimeError("the HTTP server stopped"))

    @property
    def listening(self) -> bool:
        return self._socket is not None

    @property
    def port(self) -> int:
        assert self._socket is not None
        return int(self._socket.getsockname()[1])

    def stats(self) -> dict[str, Any]:
        streams = self.hub.open if self.hub is not None else 0
        connections = len(self._server.server_state.connections) if self._server else 0
        return {"clients": connections, "streams": streams,
                "requests": self.counters["requests"],
                "request_timeouts": self.counters["request_timeouts"],
                "dropped_streams": self.hub.dropped if self.hub is not None else 0,
                "skipped_events": self.hub.skipped if self.hub is not None else 0}

    async def stop(self) -> None:
        if self.hub is not None:
            self.hub.close()  # streams end, so their connections can close
        if self._server is not None and self._task is not None:
            self._server.should_exit = True
            await self._task
        if self._socket is not None:
            self._socket.close()
            self._socket = None  # a restart listens anew

def openapi_document(gateway: GatewayLike, config: HttpConfig) -> dict[str, Any]:
    return create_app(gateway, config).openapi()
