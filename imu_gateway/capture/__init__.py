"""Event capture (docs/alarms.md, "Captures"): what every sensor and every line did
from ``pre_s`` before a trigger to ``post_s`` after it, written to one ZIP.

``Captures`` lives on the main loop.  It keeps each sensor's rows in a ring
(``ring.py``), filled from the cache's events; the buses keep their frames in rings of
their own (``imu_gateway/bus/frames.py``), copied on the bus thread when a capture is
written.  A trigger (``trigger``: ``POST /api/v1/captures``, or an alarm becoming active
through ``alarm_active``) arms a capture; ``post_s`` later the rows and frames of the
window are written to the folder on a worker thread (``archive.py``), never on the event
loop, and the listeners (MQTT's announce) are told.

A trigger while a capture is being collected joins it: it is listed in that capture's
``meta.json`` (``also``) and answered with its id; the window is not stretched, so no
capture holds more than ``pre_s + post_s``.  The next trigger after it starts a new one.

A disk that is full or read-only costs the capture, never the gateway: one warning
until a capture is written again, and the ``failed`` counter (``/metrics``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

from .. import __version__
from ..cache import EventKind, Snapshot
from ..config import CaptureConfig, GatewayConfig
from ..errors import ErrorKind, RequestFailed
from .archive import ID, SUFFIX, CaptureInfo, SensorRows, iso, new_id, retain, scan, write_capture
from .ring import SensorRing, series_fields

__all__ = ["CaptureInfo", "Captures", "FramesOf"]

log = logging.getLogger("imu_gateway.capture")

#: A line's frames: (monotonic time, direction, bytes), per bus name.
Frames = Mapping[str, list[tuple[float, str, bytes]]]
FramesOf = Callable[[], Awaitable[Frames]]
Listener = Callable[[CaptureInfo], None]


@dataclass(slots=True)
class _Pending:
    """A capture armed by a trigger, collecting until ``end``."""

    id: str
    reason: str
    alarm: str | None
    at: float
    start: float
    end: float
    rows: dict[str, list[bytes]]
    also: list[dict[str, Any]] = field(default_factory=list)


class Captures:
    """The rings, the triggers, and the captures written so far (on the main loop)."""

    def __init__(self, config: CaptureConfig, gateway: GatewayConfig,
                 frames: FramesOf, catch_up: Callable[[], None]) -> None:
        """``catch_up``: the cache's, so that the window has every sample handed over
        by its end (``Cache.catch_up``)."""
        self.config = config
        self.gateway = gateway
        self.folder = Path(config.dir)
        self.rings = {s.name: SensorRing(series_fields(s.series), config.pre_s)
                      for _, s in gateway.iter_sensors()}
        self._frames = frames
        self._catch_up = catch_up
        self._index: list[CaptureInfo] = []  # oldest first
        self._pending: _Pending | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._writing: set[asyncio.Task[None]] = set()
        self._listeners: list[Listener] = []
        self._failing = False  # warned about the disk, no capture written since
        self.counts = {"triggers": 0, "written": 0, "failed": 0}

    # ------------------------------------------------------------ the main loop's side

    async def start(self) -> None:
        """Read the folder's captures (on a worker thread); an unusable folder is
        warned about, and the gateway goes on."""
        try:
            await asyncio.to_thread(self.folder.mkdir, parents=True, exist_ok=True)
        except OSError as exc:
            self._failed(f"capture.dir {self.folder}: {exc.strerror or exc}")
        self._index = await asyncio.to_thread(scan, self.folder)

    async def stop(self) -> None:
        """Write the capture being collected now, with what it has, and wait for the
        writes under way."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._pending is not None:
            self._pending.end = time.time()
            self._write_pending()
        if self._writing:
            await asyncio.gather(*self._writing, return_exceptions=True)

    async def configure(self, config: CaptureConfig, gateway: GatewayConfig) -> None:
        """A reload.  New settings: the capture being collected is written at once with
        what it has (as at a stop, under the settings it was armed with), then they
        apply; a new folder is made and its captures listed (the old folder's stay on
        disk, no longer listed).  Each sensor kept keeps the newest rows of its ring
        that fit ``pre_s``; one added gets an empty ring; a removed one's ring goes
        (kept while a capture is collected: its rows are in it)."""
        if config != self.config:
            await self.stop()
        old_rings = self.rings
        self.config, self.gateway = config, gateway
        self.rings = {name: ring for name, ring in old_rings.items()
                      if self._pending is not None and name in self._pending.rows}
        for _, sensor in gateway.iter_sensors():
            ring = old_rings.get(sensor.name)
            fields = series_fields(sensor.series)
            if ring is None or ring.fields != fields:
                ring = SensorRing(fields, config.pre_s)
            elif ring.keep != config.pre_s:
                ring = ring.resized(config.pre_s)
            self.rings[sensor.name] = ring
        if Path(config.dir) != self.folder:
            self.folder = Path(config.dir)
            self._failing = False
            await self.start()

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        """(A cache listener: every reading and status change goes into its ring.)"""
        ring = self.rings.get(snap.name)
        row = ring.pack(kind, snap) if ring is not None else None
        if ring is None or row is None:
            return
        ring.add(row)
        if self._pending is not None:
            self._pending.rows.setdefault(snap.name, []).append(row)

    def subscribe(self, listener: Listener) -> Callable[[], None]:
        """Call ``listener(info)`` for every capture written; returns the unsubscriber."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener) if listener in self._listeners \
            else None

    # ------------------------------------------------------------ triggers

    def trigger(self, reason: str, at: float | None = None, alarm: str | None = None) -> str:
        """Arm a capture around ``at`` (seconds since the epoch; now by default); its
        id.  ``reason``: ``manual``, ``alarm``, …; ``alarm``: which one
        (``sensor/alarm``).  Joins the capture being collected, if there is one."""
        at = time.time() if at is None else at
        self.counts["triggers"] += 1
        pending = self._pending
        if pending is not None:
            pending.also.append({"reason": reason, "alarm": alarm, "t": at, "time": iso(at)})
            return pending.id
        taken = [info.id for info in self._index]
        pending = _Pending(new_id(at, taken), reason, alarm, at, at - self.config.pre_s,
                           at + self.config.post_s,
                           {name: ring.since(at - self.config.pre_s)
                            for name, ring in self.rings.items()})
        self._pending = pending
        delay = max(0.0, pending.end - time.time())
        self._timer = asyncio.get_running_loop().call_later(delay, self._write_pending)
        log.info("capture %s: %s%s; written in %.1f s", pending.id, reason,
                 f" ({alarm})" if alarm else "", delay)
        return pending.id

    def alarm_active(self, sensor: str, alarm: str, at: float | None = None) -> str | None:
        """An alarm became active: a capture, if ``capture.on_alarms`` names it (or is
        ``all``); its id."""
        wanted = self.config.on_alarms
        if wanted != "all" and alarm not in wanted:
            return None
        return self.trigger("alarm", at, f"{sensor}/{alarm}")

    def armed(self, capture_id: str) -> dict[str, Any]:
        """What ``POST /api/v1/captures`` answers of the capture being collected."""
        pending = self._pending
        if pending is None or pending.id != capture_id:  # (written at once: post_s 0)
            return {"id": capture_id, "time": iso(time.time()), "ready_in_s": 0.0}
        return {"id": capture_id, "time": iso(pending.at),
                "ready_in_s": round(max(0.0, pending.end - time.time()), 3)}

    # ------------------------------------------------------------ the list

    def listed(self) -> list[CaptureInfo]:
        """The captures kept, newest first."""
        return self._index[::-1]

    def path(self, capture_id: str) -> Path:
        """The ZIP of a capture kept.  Anything but a listed id is ``not_found``,
        before any path is made of it."""
        if not ID.fullmatch(capture_id) or all(i.id != capture_id for i in self._index):
            raise RequestFailed(ErrorKind.NOT_FOUND, f"no capture {capture_id!r}; "
                                "GET /api/v1/captures lists them")
        return self.folder / f"{capture_id}{SUFFIX}"

    # ------------------------------------------------------------ writing

    def _write_pending(self) -> None:
        self._catch_up()  # (its samples a lazy hand-over has not brought yet)
        pending, self._pending, self._timer = self._pending, None, None
        if pending is None:
            return
        task = asyncio.get_running_loop().create_task(self._write(pending),
                                                      name=f"capture {pending.id}")
        self._writing.add(task)
        task.add_done_callback(self._writing.discard)

    async def _write(self, pending: _Pending) -> None:
        frames = await self._window_frames(pending)
        info = CaptureInfo(pending.id, pending.reason, pending.alarm, pending.at, 0)
        # a reading by its wire time (it may have reached the cache later: the lazy
        # hand-over), a status row by when it was made
        sensors = [SensorRows(name, self.rings[name].fields, tuple(
            row for row in self.rings[name].unpack(rows)
            if pending.start <= (row.receive if row.wire is None else row.wire)
            <= pending.end)) for name, rows in pending.rows.items()]
        try:
            size = await asyncio.to_thread(write_capture, self.folder, info,
                                           self._meta(pending), sensors, frames)
            info = replace(info, size=size)
            kept = await asyncio.to_thread(retain, self.folder, [*self._index, info],
                                           self.config.max_files, self.config.max_mb * 1e6)
        except OSError as exc:
            self._failed(f"capture {pending.id} not written to {self.folder}: "
                         f"{exc.strerror or exc}")
            return
        self._index = kept
        self.counts["written"] += 1
        if self._failing:
            log.warning("capture %s written: %s is usable again", info.id, self.folder)
            self._failing = False
        for listener in list(self._listeners):
            try:
                listener(info)
            except Exception:  # one listener's fault stays its own
                log.exception("a capture listener failed")

    async def _window_frames(self, pending: _Pending) -> dict[str, list[tuple[float, str, bytes]]]:
        """Each line's frames in the window, in wall-clock time."""
        try:
            frames = await self._frames()
        except RequestFailed:  # a bus that is not running has none
            frames = {}
        offset = time.time() - time.monotonic()
        return {bus: [(t + offset, d, b) for t, d, b in entries
                      if pending.start <= t + offset <= pending.end]
                for bus, entries in frames.items()}

    def _failed(self, why: str) -> None:
        self.counts["failed"] += 1
        if not self._failing:
            self._failing = True
            log.warning("%s; the gateway goes on without it (counted: "
                        "imu_gateway_capture_failures)", why)

    def _meta(self, pending: _Pending) -> dict[str, Any]:
        """``meta.json``: the trigger, the window, the buses and sensors as configured
        (no secret is in them: the MQTT, HTTP and OPC UA sections are left out, and a
        port URL's user and password too), and the gateway's version."""
        return {
            "id": pending.id, "gateway_id": self.gateway.gateway_id, "version": __version__,
            "trigger": {"reason": pending.reason, "alarm": pending.alarm, "t": pending.at,
                        "time": iso(pending.at)},
            "also": pending.also,
            "window": {"from": iso(pending.start), "to": iso(pending.end),
                       "from_s": pending.start, "to_s": pending.end,
                       "pre_s": self.config.pre_s, "post_s": self.config.post_s},
            "buses": [_bus_meta(bus.model_dump(mode="json")) for bus in self.gateway.buses],
        }


def _bus_meta(bus: dict[str, Any]) -> dict[str, Any]:
    parts = urlsplit(bus["port"])
    if "@" in parts.netloc:  # ``rfc2217://user:password@host:port``
        bus["port"] = urlunsplit(parts._replace(netloc=parts.netloc.rsplit("@", 1)[1]))
    return bus
