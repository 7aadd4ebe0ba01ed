"""The captures' routes (docs/rest.md, "Captures"): the list, one capture's ZIP, and a
capture on demand (an operator's, with http.allow_commands, as for commands)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import FastAPI
from fastapi.responses import FileResponse, JSONResponse
from pydantic import BaseModel, Field

from ...errors import ErrorKind, RequestFailed
from ..common import GatewayLike
from .access import Roles
from .limits import API
from .models import ErrorOut

if TYPE_CHECKING:
    from ...capture import Captures


class CaptureOut(BaseModel):
    """One capture."""

    id: str = Field(description="its name in `GET /api/v1/captures/{id}`: the trigger's "
                    "UTC time, `20261122T034000123Z`, with `-2`, `-3`, … for a second in "
                    "the same millisecond")
    trigger: str = Field(description="`manual` (POST) or `alarm`")
    alarm: str | None = Field(description="the alarm that triggered it, `sensor/alarm`")
    time: str = Field(description="the trigger's time, ISO 8601 UTC")
    size: int = Field(description="the ZIP's size in bytes")


class CaptureArmedOut(BaseModel):
    """A capture armed: it is written ``post_s`` after the trigger."""

    id: str = Field(description="the capture's id (the one under way when a capture was "
                    "already being collected: the trigger joins it)")
    time: str = Field(description="the trigger's time, ISO 8601 UTC")
    ready_in_s: float = Field(description="seconds until it is written and listed")


def _responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorOut} for code in codes}


def capture_routes(app: FastAPI, gateway: GatewayLike, roles: Roles) -> None:
    """``GET /api/v1/captures``, ``GET /api/v1/captures/{id}``, ``POST /api/v1/captures``."""

    def captures() -> Captures:
        if gateway.captures is None:
            raise RequestFailed(ErrorKind.NOT_FOUND, "event capture is off: the config has "
                                "no capture: section (docs/alarms.md)")
        return gateway.captures

    @app.get(f"{API}/captures", response_model=list[CaptureOut], dependencies=[roles.viewer],
             responses=_responses(401, 404), summary="the captures kept, newest first",
             tags=["captures"])
    async def listed() -> list[dict[str, Any]]:
        return [info.to_json() for info in captures().listed()]

    @app.get(f"{API}/captures/{{capture_id}}", dependencies=[roles.viewer],
             response_class=FileResponse,
             responses={200: {"content": {"application/zip": {}},
                              "description": "the capture's ZIP"}, **_responses(401, 404)},
             summary="one capture: a ZIP of a CSV per sensor, frames.jsonl and meta.json",
             tags=["captures"])
    async def one(capture_id: str) -> FileResponse:
        path = captures().path(capture_id)  # refused before a path is made of it
        if not path.is_file():  # deleted since it was listed (retention, a person)
            raise RequestFailed(ErrorKind.NOT_FOUND, f"capture {capture_id} is gone")
        return FileResponse(path, media_type="application/zip",
                            filename=f"imu-gateway-capture-{capture_id}.zip")

    @app.post(f"{API}/captures", status_code=202, response_model=CaptureArmedOut,
              dependencies=[roles.commands], responses=_responses(401, 403, 404),
              summary="take a capture now: pre_s before this moment to post_s after it",
              tags=["captures"])
    async def take() -> JSONResponse:
        kept = captures()
        capture_id = kept.trigger("manual")
        armed = kept.armed(capture_id)
        return JSONResponse(armed, 202)
