"""The frame trace: one log line per exchange, for comparing with a scope or a sniffer.

    bus a: boom tx 77 04 00 59 5D | rx 77 38 00 59 … 3A (57 B, 9.8 ms) ok

Switched on per bus (``trace: true``, ``run --trace BUS``, or ``--log-level debug`` for
every bus), and at most ``TRACE_PER_S`` lines a second: a fast line makes thousands of
exchanges a second, and the log must stay readable (and cheap).  The rest are counted
and said in one line.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from .events import Trace

log = logging.getLogger("imu_gateway.trace")

TRACE_PER_S = 50
SHOWN_BYTES = 12  # of a longer answer, the first 10 and the last 2 are shown


def hex_bytes(data: bytes) -> str:
    if len(data) <= SHOWN_BYTES:
        return data.hex(" ").upper()
    return f"{data[:SHOWN_BYTES - 2].hex(' ').upper()} … {data[-2:].hex(' ').upper()}"


def format_trace(bus: str, t: Trace) -> str:
    rx = f"rx {hex_bytes(t.rx)} ({len(t.rx)} B, " if t.rx else "rx nothing ("
    placed = f" [{t.placed}]" if t.placed else ""
    return (f"bus {bus}: {t.sensor} tx {hex_bytes(t.tx)} | {rx}{t.took * 1000:.1f} ms) "
            f"{t.outcome}{placed}")


class TraceLog:
    """Writes a bus's trace lines, at most ``TRACE_PER_S`` in each second."""

    def __init__(self, bus: str) -> None:
        self.bus = bus
        self.second = -1.0  # the start of the second being counted
        self.shown = 0
        self.held = 0

    def write(self, event: Trace, now: float) -> None:
        if now - self.second >= 1.0:
            if self.held:
                log.info("bus %s: trace: %d exchanges not shown (more than %d a second)",
                         self.bus, self.held, TRACE_PER_S)
            self.second, self.shown, self.held = now, 0, 0
        if self.shown >= TRACE_PER_S:
            self.held += 1
            return
        self.shown += 1
        log.info("%s", format_trace(self.bus, event))


#: Told each ``Trace`` of the bus, on the bus thread (a traffic monitor's watch).
Watcher = Callable[[Trace], None]


class TraceTap:
    """Where a bus's Trace events go: its log (``logged``: ``trace: true``, or debug)
    and the traffic monitors watching.  The schedule makes them only while ``wanted``:
    with nobody watching and no log, an exchange costs nothing more."""

    def __init__(self, bus: str, logged: bool) -> None:
        self.log = TraceLog(bus) if logged else None
        self.watchers: list[Watcher] = []

    @property
    def wanted(self) -> bool:
        return self.log is not None or bool(self.watchers)

    def watch(self, watcher: Watcher, on: bool) -> None:
        if on:
            self.watchers.append(watcher)
        elif watcher in self.watchers:
            self.watchers.remove(watcher)

    def write(self, event: Trace, now: float) -> None:
        if self.log is not None:
            self.log.write(event, now)
        for watcher in self.watchers:
            watcher(event)
