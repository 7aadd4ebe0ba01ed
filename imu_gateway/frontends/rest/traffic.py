"""The live traffic monitor (docs/rest.md, "Traffic"): a bus's frame trace as
Server-Sent Events, at most ``TRAFFIC_PER_S`` frames a second per client.

The bus makes its trace only while someone watches (``Gateway.watch_traffic``): the
first client turns it on, the last one gone turns it off, so nobody watching costs the
line nothing."""

from __future__ import annotations

import asyncio
import contextlib
import time
import weakref
from collections import deque
from collections.abc import AsyncGenerator
from datetime import UTC, datetime
from importlib import resources
from typing import Annotated, Any

from fastapi import FastAPI, Query, Request
from fastapi.responses import HTMLResponse, StreamingResponse

from ...errors import ErrorKind, RequestFailed
from ...stats import Trace
from ..common import GatewayLike, json_bytes
from .access import Roles, peer_of
from .limits import API, KEEPALIVE_S
from .models import ErrorOut

TRAFFIC_PER_S = 50  # frames sent per client a second; the rest are counted and said
#: Traffic monitors open at once from one client address: one browser tab is one, so
#: a 17th is a leak or an attack, and it must not take the places of others.
TRAFFIC_PER_ADDRESS = 16
TRAFFIC_CLIENTS = 64  # traffic monitors open at once, for the whole gateway
QUEUE = 2 * TRAFFIC_PER_S  # frames waiting per client; past it, the oldest are skipped


def frame_json(t: Trace, wall: float) -> dict[str, Any]:
    """One exchange as the monitor shows it (``wall``: its time, epoch seconds)."""
    return {"time": datetime.fromtimestamp(wall, UTC).isoformat(timespec="milliseconds")
            .replace("+00:00", "Z"), "sensor": t.sensor, "tx": t.tx.hex(" ").upper(),
            "rx": t.rx.hex(" ").upper(), "took_ms": round(t.took * 1000, 1),
            "outcome": t.outcome, "error": t.outcome not in ("ok", "sent"),
            "placed": t.placed}


class _Watch:
    """One client's view: its filters, the frames waiting, and the second's count."""

    def __init__(self, sensor: str | None, errors: bool) -> None:
        self.sensor, self.errors = sensor, errors
        self.events: deque[bytes] = deque(maxlen=QUEUE)
        self.wake = asyncio.Event()
        self.second = -1.0  # the start of the second being counted (monotonic)
        self.shown = 0
        self.held = 0  # frames of that second not sent
        # One offset from the bus's clock to the wall's for the whole watch: the frames'
        # times keep the bus's spacing exactly (read anew per frame, a preemption
        # between the two clock reads would shift one by as much).
        self.wall = time.time() - time.monotonic()

    def on_trace(self, t: Trace) -> None:
        if (self.sensor is not None and t.sensor != self.sensor) or \
                (self.errors and t.outcome in ("ok", "sent")):
            return
        self.tick(t.at)
        if self.shown >= TRAFFIC_PER_S:
            self.held += 1
            return
        self.shown += 1
        self.events.append(b"event: frame\ndata: %s\n\n" % json_bytes(
            frame_json(t, t.at + self.wall)))
        self.wake.set()

    def tick(self, now: float) -> None:
        """A new second: the frames the last one held back are said (``skipped``)."""
        if now - self.second < 1.0:
            return
        if self.held:
            self.events.append(b"event: skipped\ndata: %s\n\n" % json_bytes(
                {"skipped": self.held, "limit_per_s": TRAFFIC_PER_S}))
            self.wake.set()
        self.second, self.shown, self.held = now, 0, 0


class _Seat:
    """One open monitor counted against its client's address, given back once."""

    def __init__(self, open_now: dict[str, int], peer: str) -> None:
        self.open_now, self.peer = open_now, peer
        open_now[peer] = open_now.get(peer, 0) + 1
        self.taken = True

    def leave(self) -> None:
        if self.taken:
            self.taken = False
            self.open_now[self.peer] -= 1
            if not self.open_now[self.peer]:
                del self.open_now[self.peer]


def traffic_routes(app: FastAPI, gateway: GatewayLike, roles: Roles) -> None:
    """``GET /api/v1/buses/{bus}/traffic``, and its page ``GET /traffic`` (with the scan)."""
    open_now: dict[str, int] = {}  # monitors open, by client address
    page = resources.files("imu_gateway") / "static" / "traffic.html"

    @app.get("/traffic", response_class=HTMLResponse, include_in_schema=False)
    async def traffic_page() -> HTMLResponse:
        return HTMLResponse(page.read_text(encoding="utf-8"))

    async def follow(bus: str, watch: _Watch, seat: _Seat) -> AsyncGenerator[bytes, None]:
        # Watching starts here, not in the route: a response never sent (its client
        # gone at once) never runs this, and must leave no watcher behind.
        try:
            stop = await gateway.watch_traffic(bus, watch.on_trace)
        except BaseException:
            seat.leave()
            raise
        try:
            yield b": watching\n\n"  # (the headers and a first line go at once)
            said = time.monotonic()
            while True:
                if not watch.events:
                    watch.wake.clear()
                    with contextlib.suppress(TimeoutError):
                        async with asyncio.timeout(1.0):
                            await watch.wake.wait()
                    watch.tick(time.monotonic())  # a quiet line: say the rest
                    if not watch.events:
                        if time.monotonic() - said >= KEEPALIVE_S:
                            said = time.monotonic()
                            yield b": keep-alive\n\n"
                        continue
                said = time.monotonic()
                yield watch.events.popleft()
        finally:
            stop()
            seat.leave()

    sse = {"content": {"text/event-stream": {}},
           "description": "`event: frame`, `data:` one exchange (time, sensor, tx, rx, "
                          "took_ms, outcome, error, placed); `event: skipped`, `data:` how "
                          f"many frames of the last second were not sent (past "
                          f"{TRAFFIC_PER_S} a second)"}

    @app.get(f"{API}/buses/{{bus}}/traffic", dependencies=[roles.viewer],
             response_class=StreamingResponse,
             responses={200: sse, **{c: {"model": ErrorOut} for c in (401, 404, 429, 503)}},
             summary="Server-Sent Events: the bus's frames as they go (a traffic monitor)")
    async def traffic(request: Request, bus: str, sensor: Annotated[str | None, Query(
            description="only this sensor's exchanges")] = None,
                      errors: Annotated[bool, Query(
                          description="only the exchanges that failed")] = False,
                      ) -> StreamingResponse:
        buses = [b.name for b in gateway.config.buses]
        if bus not in buses:
            raise RequestFailed(ErrorKind.NOT_FOUND, f"no bus {bus!r} (the buses: "
                                f"{', '.join(buses) or 'none'})")
        if sensor is not None:
            gateway.cache.snapshot(sensor)  # (unknown_sensor, 404)
        peer = peer_of(request)
        if open_now.get(peer, 0) >= TRAFFIC_PER_ADDRESS:
            raise RequestFailed(ErrorKind.TOO_MANY_WATCHERS, (
                f"{TRAFFIC_PER_ADDRESS} traffic monitors are open from {peer} already: "
                "close one (a page or tab showing the traffic) and try again"))
        if sum(open_now.values()) >= TRAFFIC_CLIENTS:
            raise RequestFailed(ErrorKind.TOO_MANY_STREAMS,
                                f"{TRAFFIC_CLIENTS} traffic monitors are open")
        seat = _Seat(open_now, peer)
        stream = follow(bus, _Watch(sensor, errors), seat)
        # The seat is taken here, where the check is (no await between them: 17
        # requests at once cannot all pass it); it is left when the stream ends, or
        # when a stream never started is dropped (a client gone before its answer).
        weakref.finalize(stream, seat.leave)
        return StreamingResponse(stream, media_type="text/event-stream",
                                 headers={"X-Accel-Buffering": "no"})
