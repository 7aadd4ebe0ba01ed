"""The procedures' routes (docs/wizards.md, docs/rest.md "Procedures"): a calibration
or setup wizard as a resource.  ``POST …/procedures/{procedure}`` starts one (an
operator's: the bearer token and ``http.allow_commands``, as commands; an admin's too for
those that change the config: the address and baud changes); it runs here, one
catalogue command after the other through ``gateway.command`` (``imu_gateway.procedures``
says which and when), a config change through the gateway's reloader (as ``PUT
/api/v1/config``); ``GET`` shows it, ``…/events`` streams it, ``DELETE`` cancels it.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import itertools
import logging
from collections import OrderedDict
from collections.abc import AsyncGenerator, Awaitable, Callable
from dataclasses import dataclass, field
from importlib import resources
from typing import Annotated, Any, Protocol, runtime_checkable

from fastapi import Depends, FastAPI, Request
from fastapi.responses import HTMLResponse, JSONResponse, StreamingResponse
from pydantic import BaseModel, Field

from ...cache import EventKind, Snapshot
from ...commands import commands_for
from ...errors import ConfigError, ErrorKind, RequestFailed
from ...procedures import (
    PROCEDURES,
    ChangeConfig,
    Placement,
    Run,
    SendCommand,
    available,
    validate,
)
from ..common import GatewayLike, json_bytes, peer_json
from .access import Roles
from .limits import API, KEEPALIVE_S, MAX_BODY
from .models import ErrorOut

log = logging.getLogger("imu_gateway.http")

#: Finished procedures kept for ``GET`` (the oldest go first).
KEEP = 32
#: A procedure's stream sends its state at most this often (a circle's readings come
#: at the poll rate; a page needs a few pictures a second).
EVENT_INTERVAL_S = 0.2


@runtime_checkable
class _Reloader(Protocol):
    """What a procedure that changes the config needs of ``reload.Reloader``."""

    def shown(self) -> Any: ...

    async def put(self, data: Any, dry_run: bool) -> Any: ...


class ProcedureOut(BaseModel):
    """A procedure and where it stands (docs/wizards.md)."""

    id: str = Field(description="its number in `…/procedures/{procedure}/{id}`")
    sensor: str
    procedure: str = Field(description="gyro_calibration, mag_calibration, zero, "
                           "change_address or change_baudrate")
    state: str = Field(description="running, done, failed or cancelled")
    step: str | None = Field(description="the step under way (running only)")
    steps: list[str | None]
    prompt: str = Field(description="what the person should do now")
    countdown_s: float | None = Field(description="seconds left of a countdown")
    elapsed_s: float
    answers: dict[str, Any] = Field(description="each command's answer, by command; "
                                    "`config`: the reload's outcome (an address or baud "
                                    "change)")
    angles: dict[str, dict[str, float]] = Field(description="zero: the angles before and after")
    coverage_percent: float | None = Field(description="magnetic calibration: the share of "
                                           "the circle's 36 sectors of 10° covered")
    points: list[list[float]] | None = Field(description="magnetic calibration: [mag_x, "
                                             "mag_y] pairs, one per degree at most")
    quality: dict[str, float] | None = Field(description="the circle's centre offset and "
                                             "ellipse ratio, once it is whole")
    offers: list[str] = Field(description="commands offered once done (save)")
    error: str | None
    kind: str | None


@dataclass(eq=False)
class _Live:
    """A procedure this server runs, and who is told when it changes."""

    id: str
    sensor: str
    run: Run
    version: int = 0
    changed: asyncio.Event = field(default_factory=asyncio.Event)  # a new version
    wake: asyncio.Event = field(default_factory=asyncio.Event)  # the driver: an input
    task: asyncio.Task[None] | None = None

    def touch(self) -> None:
        self.version += 1
        self.changed.set()
        self.wake.set()

    @property
    def path(self) -> str:
        return f"{API}/sensors/{self.sensor}/procedures/{self.run.spec.name}/{self.id}"

    def to_json(self) -> dict[str, Any]:
        now = asyncio.get_running_loop().time()
        return {"id": self.id, "sensor": self.sensor, **self.run.to_json(now)}


class Procedures:
    """The procedures of one server: at most one running per sensor, the last ``KEEP``
    kept."""

    def __init__(self, gateway: GatewayLike) -> None:
        self.gateway = gateway
        self.runs: OrderedDict[str, _Live] = OrderedDict()
        self._ids = itertools.count(1)

    def get(self, sensor: str, procedure: str, run_id: str) -> _Live:
        live = self.runs.get(run_id)
        if live is None or live.sensor != sensor or live.run.spec.name != procedure:
            raise RequestFailed(ErrorKind.NOT_FOUND, f"{sensor} has no {procedure} {run_id!r}")
        return live

    def start(self, sensor: str, name: str, args: Any) -> _Live:
        bus = next(b for b, s in self.gateway.config.iter_sensors() if s.name == sensor)
        series = self.gateway.sensors[sensor].series
        where = Placement.of(self.gateway.config, sensor, {
            s.name: self.gateway.sensor_stats(s.name).address for s in bus.sensors})
        spec, values = validate(name, args, series, commands_for(series, bus.protocol), where)
        for other in self.runs.values():
            if other.sensor == sensor and not other.run.over:
                raise RequestFailed(ErrorKind.BUSY, f"{sensor} is in {other.run.spec.name} "
                                    f"{other.id}: wait for it, or cancel it ({other.path})")
        loop = asyncio.get_running_loop()
        live = _Live(str(next(self._ids)), sensor, Run(spec, values, loop.time(), where))
        self.runs[live.id] = live
        while len(self.runs) > KEEP:
            oldest = next(iter(self.runs.values()))
            if not oldest.run.over:
                break
            del self.runs[oldest.id]
        live.task = asyncio.create_task(self._drive(live), name=f"procedure {live.id}")
        log.info("procedure %s started on %s", live.id, sensor)
        return live

    async def _drive(self, live: _Live) -> None:
        """Do what the run asks until it is over: commands through the gateway, waits
        on the sensor's events, the person's input and the clock."""
        loop, cache, run = asyncio.get_running_loop(), self.gateway.cache, live.run

        def observe(snap: Snapshot) -> None:
            before = (run.state, run.index, len(run.circle.points), run.seq)
            run.observe(snap.seq, snap.reading, snap.busy, loop.time())
            if (run.state, run.index, len(run.circle.points), run.seq) != before:
                live.touch()

        def heard(kind: EventKind, snap: Snapshot) -> None:
            if snap.name == live.sensor and kind is not EventKind.SETTINGS:
                observe(snap)

        unsubscribe = cache.subscribe(heard)
        try:
            observe(cache.snapshot(live.sensor))
            while (action := run.action(loop.time())) is not None:
                live.touch()
                if isinstance(action, SendCommand):
                    run.sending()
                    result = await self.gateway.command(live.sensor, action.command,
                                                        action.args)
                    run.answered(result, loop.time())
                    observe(cache.snapshot(live.sensor))  # busy from the answer on
                    continue
                if isinstance(action, ChangeConfig):
                    run.sending()
                    outcome, error = await self._reconfigure(action)
                    run.reconfigured(outcome, error, loop.time())
                    continue
                live.wake.clear()
                wait = None if action.until is None else max(0.0, action.until - loop.time())
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(wait):
                        await live.wake.wait()
        except Exception as exc:  # (a bug: the procedure says so, the server goes on)
            log.exception("procedure %s failed", live.id)
            run.cancel(loop.time(), force=True)
            run.cleaning, run.error = False, f"internal error: {exc}"
        finally:
            unsubscribe()
            log.info("procedure %s on %s: %s%s", live.id, live.sensor, run.state.value,
                     f" ({run.error})" if run.error else "")
            live.touch()

    async def _reconfigure(self, action: ChangeConfig
                           ) -> tuple[dict[str, Any] | None, str | None]:
        """The config with the change, applied and saved by the reloader: its outcome
        (as ``PUT /api/v1/config`` answers), or why it could not be."""
        reloader = getattr(self.gateway, "reloader", None)
        if not isinstance(reloader, _Reloader):
            return None, "this gateway cannot change its config"
        try:
            # the config as written, secrets as ***: the reloader puts them back
            data = action.change.applied_to(reloader.shown())
            outcome = await reloader.put(data, dry_run=False)
        except ConfigError as exc:
            return None, f"the new config was refused: {'; '.join(exc.problems)}"
        except (ValueError, OSError) as exc:
            return None, str(exc)
        log.info("procedure: %s set to %s on %s", action.change.key, action.change.value,
                 action.change.where())
        answer: dict[str, Any] = outcome.to_json()
        return {"applied": answer["applied"], "saved": answer["saved"],
                "note": answer["note"], "summary": answer["diff"]["summary"]}, None

    async def events(self, live: _Live) -> AsyncGenerator[bytes, None]:
        """Server-Sent Events: the state whenever it changed (at most every
        ``EVENT_INTERVAL_S``), ``event: end`` with the final one."""
        seen = -1
        while True:
            if live.version == seen:
                live.changed.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(KEEPALIVE_S):
                        await live.changed.wait()
                if live.version == seen:
                    yield b": keep-alive\n\n"
                    continue
            seen = live.version
            over = live.run.over and live.task is not None and live.task.done()
            yield b"event: %s\ndata: %s\n\n" % (b"end" if over else b"progress",
                                               json_bytes(live.to_json()))
            if over:
                return
            await asyncio.sleep(EVENT_INTERVAL_S)

    def close(self) -> None:
        for live in self.runs.values():
            if live.task is not None:
                live.task.cancel()


async def _arguments(request: Request) -> Any:
    """The JSON body, at most ``MAX_BODY`` bytes, read only after the access check (a
    route's own dependencies run first)."""
    raw = bytearray()
    async for chunk in request.stream():
        raw += chunk
        if len(raw) > MAX_BODY:
            raise RequestFailed(ErrorKind.TOO_LARGE, f"the body is over {MAX_BODY} bytes")
    if not raw.strip():
        return None
    try:
        return peer_json(bytes(raw))
    except (ValueError, RecursionError):
        raise RequestFailed(ErrorKind.BAD_ARGUMENTS, "body: not JSON (send a JSON object "
                            "of the procedure's arguments, or nothing)") from None


def _responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorOut} for code in codes}


def procedure_routes(app: FastAPI, gateway: GatewayLike, roles: Roles) -> None:
    """The procedure routes under ``/api/v1/sensors/{name}/procedures``."""
    procedures = Procedures(gateway)
    app.router.on_shutdown.append(procedures.close)
    base = f"{API}/sensors/{{name}}/procedures"
    tags: list[str | enum.Enum] = ["procedures"]

    def live_of(name: str, procedure: str, run_id: str) -> _Live:
        gateway.cache.snapshot(name)  # an unknown sensor: 404 unknown_sensor
        return procedures.get(name, procedure, run_id)

    @app.get(base, dependencies=[roles.viewer], responses=_responses(401, 404), tags=tags,
             summary="the procedures this sensor can run, and those run lately")
    async def listed(name: str) -> dict[str, Any]:
        gateway.cache.snapshot(name)
        bus = next(b for b, s in gateway.config.iter_sensors() if s.name == name)
        series = gateway.sensors[name].series
        able = available(series, commands_for(series, bus.protocol))
        return {"available": able, "runs": [live.to_json() for live in
                                            procedures.runs.values() if live.sensor == name]}

    _wizards_page(app)
    def begin(name: str, procedure: str, args: Any) -> JSONResponse:
        gateway.cache.snapshot(name)
        live = procedures.start(name, procedure, args)
        return JSONResponse(live.to_json(), 201, headers={"Location": live.path})

    _admin_routes(app, base, roles, begin)  # (matched before the one for the others)

    @app.post(f"{base}/{{procedure}}", status_code=201, response_model=ProcedureOut,
              dependencies=[roles.commands], tags=tags,
              responses=_responses(401, 403, 404, 409, 413, 422),
              summary="start a procedure (gyro_calibration, mag_calibration, zero)")
    async def start(name: str, procedure: str,
                    args: Annotated[Any, Depends(_arguments)]) -> JSONResponse:
        spec = PROCEDURES.get(procedure)
        if spec is not None and spec.admin:  # (its own route is matched first)
            raise RequestFailed(ErrorKind.FORBIDDEN, f"{procedure} is an admin's")
        return begin(name, procedure, args)

    @app.get(f"{base}/{{procedure}}/{{run_id}}", response_model=ProcedureOut,
             dependencies=[roles.viewer], tags=tags, responses=_responses(401, 404),
             summary="a procedure's state")
    async def one(name: str, procedure: str, run_id: str) -> dict[str, Any]:
        return live_of(name, procedure, run_id).to_json()

    @app.get(f"{base}/{{procedure}}/{{run_id}}/events", dependencies=[roles.viewer], tags=tags,
             response_class=StreamingResponse,
             responses={200: {"content": {"text/event-stream": {}},
                              "description": "`event: progress` with the state as `data:` "
                                             "when it changes; `event: end` with the last"},
                        **_responses(401, 404)},
             summary="Server-Sent Events: a procedure's progress")
    async def events(name: str, procedure: str, run_id: str) -> StreamingResponse:
        return StreamingResponse(procedures.events(live_of(name, procedure, run_id)),
                                 media_type="text/event-stream",
                                 headers={"X-Accel-Buffering": "no"})

    @app.post(f"{base}/{{procedure}}/{{run_id}}/finish", response_model=ProcedureOut,
              dependencies=[roles.commands], tags=tags, responses=_responses(401, 403, 404,
                                                                                 409),
              summary="magnetic calibration: end the circle where it stands")
    async def finish(name: str, procedure: str, run_id: str) -> dict[str, Any]:
        live = live_of(name, procedure, run_id)
        live.run.user("finish", asyncio.get_running_loop().time())
        live.touch()
        return live.to_json()

    @app.delete(f"{base}/{{procedure}}/{{run_id}}", response_model=ProcedureOut,
                dependencies=[roles.commands], tags=tags,
                responses=_responses(401, 403, 404, 409),
                summary="cancel a procedure (a magnetic calibration is cleared; an address "
                        "or baud change only before its command is sent: 409 after)")
    async def cancel(name: str, procedure: str, run_id: str) -> dict[str, Any]:
        live = live_of(name, procedure, run_id)
        live.run.cancel(asyncio.get_running_loop().time())
        live.touch()
        return live.to_json()


def _wizards_page(app: FastAPI) -> None:
    @app.get("/wizards", response_class=HTMLResponse, include_in_schema=False)
    async def page() -> HTMLResponse:
        return HTMLResponse((resources.files("imu_gateway") / "static" / "wizards.html")
                            .read_text(encoding="utf-8"))


def _admin_routes(app: FastAPI, base: str, roles: Roles,
                  begin: Callable[[str, str, Any], JSONResponse]) -> None:
    """The procedures that change the config are an admin's (and send commands: commands
    must be on), each its own route: ``POST {base}/change_address``, …"""
    for spec in PROCEDURES.values():
        if spec.admin:
            app.post(f"{base}/{spec.name}", status_code=201, response_model=ProcedureOut,
                     dependencies=[roles.commands, roles.admin], tags=["procedures"],
                     responses=_responses(401, 403, 404, 409, 413, 422),
                     summary=f"start {spec.name}: {spec.summary}")(_start_of(spec.name, begin))


def _start_of(procedure: str, begin: Callable[[str, str, Any], JSONResponse],
              ) -> Callable[..., Awaitable[JSONResponse]]:
    """The route that starts ``procedure``."""
    async def start(name: str, args: Annotated[Any, Depends(_arguments)]) -> JSONResponse:
        return begin(name, procedure, args)
    return start
