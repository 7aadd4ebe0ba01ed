"""A scan of a line, for the front ends (REST's ``POST /api/v1/scan``).

The scan is ``bus/scan.py``'s, the one ``imu-gateway scan`` runs: blocking reads and
writes on the port, so it runs on a thread of its own and hands its progress and its
finds to the gateway's loop as ``ScanEvent``s.  Every event is kept (a scan makes a few
hundred at most), so a client that connects late, or twice, sees the whole scan.

A port one of the gateway's own buses uses is released by that bus for the scan and
reopened after it (``pause`` and ``resume``, the bus's): nothing else may write to the
line meanwhile, and the scan's exclusive open would fail on a port the bus holds.  The
scan's first request waits until the answer to the bus's last one can no longer come.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import os
import threading
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import serial

from .bus.scan import Found, Progress, Throttle, plan, port_problem, scan, time_left
from .errors import GatewayError
from .model import WireProtocol

log = logging.getLogger("imu_gateway.scan")

#: At most one progress event in this many seconds (each step's start always goes).
PROGRESS_EVERY = 0.5
#: The longest the scan waits for the paused bus's last answer (a bus with a learned
#: timeout holds the line about 0.9 s at most; a fixed ``timeout_ms`` can be longer).
QUIET_MAX = 2.0
_ids = itertools.count(1)


@dataclass(frozen=True, slots=True)
class ScanRequest:
    port: str
    protocols: tuple[WireProtocol, ...]
    bauds: tuple[int, ...]
    addresses: tuple[int, ...] | None  # None: every address the protocol has
    margin: float  # seconds an address is waited for past its frames' wire time

    def estimate(self) -> float:
        """Seconds the whole scan takes if nothing answers (``bus.scan.time_left``)."""
        steps = plan(self.protocols, self.bauds, self.addresses)
        return time_left(steps, 0, None, self.margin) if steps else 0.0


@dataclass(frozen=True, slots=True)
class ScanEvent:
    """``progress``, ``found``, and one last: ``done``, ``failed`` or ``cancelled``."""

    kind: str
    data: dict[str, Any]

    @property
    def last(self) -> bool:
        return self.kind in ("done", "failed", "cancelled")


class _Cancelled(GatewayError):
    """Raised in the scan's thread (from its progress report) to end it; it never
    leaves this module (a leaf of ``imu_gateway.errors``'s tree all the same)."""


#: What pauses the bus on the scanned port (it returns when the line is quiet, on the
#: loop's clock), and what resumes it.
Pause = Callable[[str], Awaitable[float]]
Resume = Callable[[], Awaitable[None]]


@dataclass(eq=False)
class ScanJob:
    request: ScanRequest
    bus: str | None  # the gateway's bus on that port, paused for the scan
    pause: Pause | None = None
    resume: Resume | None = None
    id: str = field(default_factory=lambda: str(next(_ids)))
    events: list[ScanEvent] = field(default_factory=list)
    _cancel: threading.Event = field(default_factory=threading.Event)
    _changed: asyncio.Event = field(default_factory=asyncio.Event)
    task: asyncio.Task[None] | None = None

    @property
    def finished(self) -> bool:
        return bool(self.events) and self.events[-1].last

    def start(self) -> None:
        self.task = asyncio.get_running_loop().create_task(self._run())

    def cancel(self) -> None:
        """End the scan at its next address (the port is closed, the bus resumed)."""
        self._cancel.set()

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            if self.pause is not None:
                quiet = await self.pause(f"polling paused for a scan of "
                                         f"{self.request.port} (scan {self.id})")
                # The bus's last request may be answered until then: the scan's first
                # would meet that answer, or hear it and take it for a stream's frame.
                await asyncio.sleep(min(max(0.0, quiet - loop.time()), QUIET_MAX))
            await asyncio.to_thread(self._scan, loop)
        except asyncio.CancelledError:
            # The gateway stops (its loop's last tasks are cancelled, then its threads
            # joined): the scan must end now, not after its minutes.
            self._cancel.set()
            raise
        except Exception as exc:  # a bug: said, and the bus still resumes
            log.exception("scan %s: internal error", self.id)
            self._add(ScanEvent("failed", {"error": f"internal error ({exc})"}))
        finally:
            if self.resume is not None:
                await self.resume()

    def _scan(self, loop: asyncio.AbstractEventLoop) -> None:
        """On the scan's thread: the scan, each event handed to ``loop``."""
        def hand(event: ScanEvent) -> None:
            loop.call_soon_threadsafe(self._add, event)

        def progress(p: Progress) -> None:
            if self._cancel.is_set():
                raise _Cancelled
            hand(ScanEvent("progress", _progress_json(p)))

        r = self.request
        try:
            for found in scan(r.port, r.protocols, r.bauds, r.addresses, r.margin,
                              Throttle(progress, PROGRESS_EVERY)):
                hand(ScanEvent("found", found_json(found)))
                if self._cancel.is_set():
                    raise _Cancelled
        except _Cancelled:
            hand(ScanEvent("cancelled", {}))
        except (serial.SerialException, OSError) as exc:
            error = port_problem(r.port, exc) if isinstance(exc, serial.SerialException) \
                else f"{r.port}: {exc}"
            hand(ScanEvent("failed", {"error": error}))
        else:
            hand(ScanEvent("done", {}))

    def _add(self, event: ScanEvent) -> None:
        if self.finished:
            return
        self.events.append(event)
        self._changed.set()

    async def follow(self) -> AsyncIterator[ScanEvent]:
        """Every event of the scan, from its first, until its last."""
        sent = 0
        while True:
            while sent < len(self.events):
                sent += 1
                yield self.events[sent - 1]
                if self.events[sent - 1].last:
                    return
            self._changed.clear()
            await self._changed.wait()


def same_port(a: str, b: str) -> bool:
    """Whether two port names are one port (``/dev/serial/by-id/…`` and ``/dev/ttyUSB0``
    are); a pyserial URL is only itself."""
    if "://" in a or "://" in b:
        return a == b
    return os.path.realpath(a) == os.path.realpath(b)


def _progress_json(p: Progress) -> dict[str, Any]:
    return {"protocol": p.step.protocol.name.lower(), "baudrate": p.step.baudrate,
            "address": p.address, "asked": p.asked, "of": len(p.step.addresses),
            "seconds_left": round(p.seconds_left, 1), "text": p.line()}


def found_json(found: Found) -> dict[str, Any]:
    return {"protocol": found.protocol.name.lower(), "baudrate": found.baudrate,
            "address": found.address, "series": found.series}
