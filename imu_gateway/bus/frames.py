"""A line's recent frames, for event capture (docs/alarms.md, "Captures").

Kept only when the config has ``capture:``: the bus master's link is then a
``RecordingLink``, which notes each request written and each piece of bytes read, on
the bus thread, in a ``deque`` with a fixed ``maxlen``: one append per write and per
read, no lock, no copy, and memory that cannot grow.  The capture reads it through the
bus runner's call (``BusRunner.frames``), which copies it on the bus thread: a deque
iterated while another thread appends to it fails, so it is never read from the main
loop.

Each entry is ``(monotonic time, direction, bytes)``, the times the bus master's own
(a request's when its write returned, bytes' when they were read).  The direction says
what the bus knew when bytes came in: ``rx`` while one of its requests was waiting for
its answer (the answer, garbage and all), ``rx-unasked`` otherwise (a stream frame, a
late answer, noise).  A replay answers each request with the ``rx`` after it and plays
the unasked ones at their times (``imu_gateway/simulator/replay.py``).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

from .link import OnBytes, OnLost, OnOpen, SerialLink
from .reactor import Reactor

TX, RX, RX_UNASKED = "tx", "rx", "rx-unasked"
#: (monotonic time, TX | RX | RX_UNASKED, the bytes)
Frame = tuple[float, str, bytes]
#: The smallest exchange that can fill a line: a 5-byte request and a 5-byte answer,
#: 10 bits a byte; two entries each.  A line's ring holds what ``seconds`` of that take.
_ENTRIES_PER_BAUD = 2 / (10 * 10)


def ring_size(seconds: float, baudrate: int) -> int:
    """The entries a ring needs to hold ``seconds`` of a full line at ``baudrate``."""
    return max(64, math.ceil(seconds * baudrate * _ENTRIES_PER_BAUD))


class RecordingLink(SerialLink):
    """A ``SerialLink`` that keeps its last ``size`` frames.  ``asked()`` says, on the
    bus thread, whether a request is waiting for its answer."""

    def __init__(self, port: str, baudrate: int, *, rs485: bool, size: int,
                 asked: Callable[[], bool]) -> None:
        super().__init__(port, baudrate, rs485=rs485)
        self.frames: deque[Frame] = deque(maxlen=size)
        self._asked = asked

    def open(self, reactor: Reactor, on_bytes: OnBytes, on_lost: OnLost,
             on_open: OnOpen) -> None:
        frames, asked = self.frames, self._asked

        def heard(data: bytes, at: float) -> None:
            frames.append((at, RX if asked() else RX_UNASKED, data))
            on_bytes(data, at)

        super().open(reactor, heard, on_lost, on_open)

    def write(self, data: bytes, expect: int = 0, look_after: float = 0.0,
              latest: float = math.inf) -> bool:
        if not super().write(data, expect, look_after, latest):
            return False
        self.frames.append((time.monotonic(), TX, data))
        return True

    def copy(self) -> list[Frame]:
        """(On the bus thread: the runner's call.)"""
        return list(self.frames)
