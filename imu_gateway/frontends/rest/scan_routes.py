"""Scanning a line from the browser (docs/rest.md, "Scan"): ``POST /api/v1/scan``
starts one (the admin's: the bearer token), ``GET /api/v1/scan/{id}/events`` follows
it as Server-Sent Events, ``POST /api/v1/scan/{id}/cancel`` cancels it.

A port one of the gateway's buses uses is scanned only when the request says
``confirm: true``: that bus's polling pauses for the scan, and the refusal says so,
with the time the scan takes, before anything stops."""

from __future__ import annotations

from collections.abc import AsyncGenerator
from typing import Any

from fastapi import FastAPI
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import BaseModel, Field, model_validator

from ...errors import ErrorKind, RequestFailed
from ...model import WireProtocol
from ...scanning import ScanJob, ScanRequest, same_port
from ..common import GatewayLike, json_bytes
from .access import Roles
from .limits import API
from .models import ErrorOut

KEEP = 8  # finished scans kept for GET (their events), besides those under way
BAUDS = (2400, 4800, 9600, 19200, 38400, 57600, 115200, 460800)


class ScanIn(BaseModel):
    """What to scan: as `imu-gateway scan`'s options."""

    model_config = {"extra": "forbid", "strict": True}  # (0 is not false, "5" not 5)
    port: str = Field(min_length=1, max_length=256, description="a device path or a "
                      "pyserial URL")
    protocols: list[str] = Field(default=["native", "modbus"], min_length=1,
                                 description="`native`, `modbus`")
    bauds: list[int] = Field(default=[9600, 115200, 460800, 19200, 38400, 57600, 4800, 2400],
                             min_length=1, description="in the order they are tried")
    first_address: int = Field(default=0, ge=0, le=255)
    last_address: int = Field(default=255, ge=0, le=255)
    margin_ms: float = Field(default=100.0, ge=0, le=2000,
                             description="how long past its wire time an address is "
                                         "waited for")
    confirm: bool = Field(default=False, description="scan a port one of the gateway's "
                          "buses uses: its polling pauses for the scan")

    @model_validator(mode="after")
    def _check(self) -> ScanIn:
        bad = [p for p in self.protocols if p not in ("native", "modbus")]
        if bad:
            raise ValueError(f"protocols: {bad[0]!r} is not native or modbus")
        wrong = [b for b in self.bauds if b not in BAUDS]
        if wrong:
            raise ValueError(f"bauds: {wrong[0]} is not one of {', '.join(map(str, BAUDS))}")
        if self.first_address > self.last_address:
            raise ValueError("first_address is above last_address")
        return self

    def request(self) -> ScanRequest:
        addresses = range(self.first_address, self.last_address + 1)
        return ScanRequest(
            self.port, tuple(WireProtocol[p.upper()] for p in self.protocols),
            tuple(self.bauds), None if len(addresses) == 256 else tuple(addresses),
            self.margin_ms / 1000)


class ScanOut(BaseModel):
    """A scan: where to follow it, and what it stops."""

    id: str
    port: str
    paused_bus: str | None = Field(description="the gateway's bus on that port, whose "
                                   "polling pauses for the scan (null: a free port)")
    estimate_s: float = Field(description="how long the scan takes if nothing answers")
    events: str = Field(description="its Server-Sent Events")
    finished: bool
    found: list[dict[str, Any]] = Field(description="the sensors found so far")


def _out(job: ScanJob) -> dict[str, Any]:
    return {"id": job.id, "port": job.request.port, "paused_bus": job.bus,
            "estimate_s": round(job.request.estimate(), 1),
            "events": f"{API}/scan/{job.id}/events", "finished": job.finished,
            "found": [e.data for e in job.events if e.kind == "found"]}


def scan_routes(app: FastAPI, gateway: GatewayLike, roles: Roles) -> None:
    """``POST /api/v1/scan``, ``GET /api/v1/scan`` and ``…/{id}``, ``…/events``,
    ``…/cancel``."""
    jobs: dict[str, ScanJob] = {}
    errors: dict[int | str, dict[str, Any]] = {
        c: {"model": ErrorOut} for c in (401, 403, 404, 409, 422)}

    def job_or_404(scan_id: str) -> ScanJob:
        if scan_id not in jobs:
            raise RequestFailed(ErrorKind.NOT_FOUND, f"no scan {scan_id!r} (kept: the last "
                                f"{KEEP} finished and those under way)")
        return jobs[scan_id]

    @app.post(f"{API}/scan", status_code=202, response_model=ScanOut,
              dependencies=[roles.admin], responses=errors, tags=["scan"],
              summary="scan a port for sensors (a bus on that port pauses: confirm)")
    async def start(body: ScanIn) -> JSONResponse:
        request = body.request()
        if any(same_port(j.request.port, request.port) and not j.finished
               for j in jobs.values()):
            raise RequestFailed(ErrorKind.BUSY, f"a scan of {request.port} is under way")
        job = gateway.scan(request)
        if job.bus is not None and not body.confirm:
            raise RequestFailed(ErrorKind.BUSY, (
                f"{request.port} is bus {job.bus}'s port: its polling pauses for the scan "
                f"(about {request.estimate():.0f} s if nothing answers) and resumes after; "
                "send the request again with \"confirm\": true to go ahead"))
        for old in [j for j in jobs.values() if j.finished][:-KEEP or None]:
            del jobs[old.id]
        jobs[job.id] = job
        job.start()
        return JSONResponse(_out(job), 202)

    @app.get(f"{API}/scan", response_model=list[ScanOut], dependencies=[roles.viewer],
             responses=errors, tags=["scan"],
             summary="the scans under way and the last finished ones, oldest first")
    async def listed() -> list[dict[str, Any]]:
        return [_out(job) for job in jobs.values()]

    @app.get(f"{API}/scan/{{scan_id}}", response_model=ScanOut, dependencies=[roles.viewer],
             responses=errors, tags=["scan"], summary="a scan: what it found so far")
    async def one(scan_id: str) -> dict[str, Any]:
        return _out(job_or_404(scan_id))

    @app.post(f"{API}/scan/{{scan_id}}/cancel", response_model=ScanOut,
              dependencies=[roles.admin], responses=errors, tags=["scan"],
              summary="cancel a scan (the bus it paused resumes); it stays listed")
    async def cancel(scan_id: str) -> dict[str, Any]:
        job = job_or_404(scan_id)
        job.cancel()
        return _out(job)

    async def follow(job: ScanJob) -> AsyncGenerator[bytes, None]:
        async for event in job.follow():
            yield b"event: %s\ndata: %s\n\n" % (event.kind.encode(), json_bytes(event.data))

    @app.get(f"{API}/scan/{{scan_id}}/events", dependencies=[roles.viewer],
             response_class=StreamingResponse, tags=["scan"],
             responses={200: {"content": {"text/event-stream": {}}, "description": (
                 "`progress` (protocol, baudrate, address, asked, of, seconds_left, text), "
                 "`found` (protocol, baudrate, address, series), then one of `done`, "
                 "`failed` (error) or `cancelled`; from the scan's start")}, **errors},
             summary="Server-Sent Events: a scan's progress and finds")
    async def events(scan_id: str) -> StreamingResponse:
        return StreamingResponse(follow(job_or_404(scan_id)), media_type="text/event-stream",
                                 headers={"X-Accel-Buffering": "no"})
