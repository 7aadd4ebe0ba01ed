"""A line's recent frames, for event capture (docs/alarms.md, "Captures").

Kept only when the config has ``capture:``.  The bus master appends each request it
wrote and each piece of bytes it read, on the bus thread, to a ``deque`` with a fixed
``maxlen``: one append per write and per read, no lock, no copy, and memory that
cannot grow.  The capture reads it through the bus runner's call (``BusRunner.frames``),
which copies it on the bus thread: a deque iterated while another thread appends to it
fails, so it is never read from the main loop.

Each entry is ``(monotonic time, direction, bytes)``.  The direction says what the bus
knew when the bytes came in: ``rx`` while one of its requests was waiting for its answer
(the answer, garbage and all), ``rx-unasked`` otherwise (a stream frame, a late answer,
noise).  A replay answers each request with the ``rx`` after it and plays the unasked
ones at their times (``imu_gateway/simulator/replay.py``).
"""

from __future__ import annotations

import math
from collections import deque

TX, RX, RX_UNASKED = "tx", "rx", "rx-unasked"
#: (monotonic time, TX | RX | RX_UNASKED, the bytes)
Frame = tuple[float, str, bytes]
#: The smallest exchange that can fill a line: a 5-byte request and a 5-byte answer,
#: 10 bits a byte; two entries each.  A line's ring holds what ``seconds`` of that take.
_ENTRIES_PER_BAUD = 2 / (10 * 10)


def ring_size(seconds: float, baudrate: int) -> int:
    """The entries a ring needs to hold ``seconds`` of a full line at ``baudrate``."""
    return max(64, math.ceil(seconds * baudrate * _ENTRIES_PER_BAUD))


class FrameRing:
    """The frames of one line, the newest ``size`` (appended on the bus thread only)."""

    def __init__(self, size: int) -> None:
        self.entries: deque[Frame] = deque(maxlen=size)

    def copy(self) -> list[Frame]:
        """(On the bus thread: the runner's call.)"""
        return list(self.entries)
