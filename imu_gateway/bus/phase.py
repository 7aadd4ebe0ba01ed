"""When a stream's frames really end, from when this machine sees them.

A streaming sensor sends a frame every ``period`` on its own clock.  Each frame is
seen late by a varying amount: the USB adapter's latency timer, the kernel handing the
bytes on, a reader thread that waits for a busy CPU.  Usually that is a fraction of a
millisecond; on a loaded machine it is now and then most of a period (measured on the
test machine with four CPU burners: frames seen up to 9.5 ms late at 100 Hz).

Two mistakes put a request on top of a frame, and this module avoids both:

* **Taking a very late frame for one that just ended.**  A frame seen 9.5 ms late at
  100 Hz looks like the next one, seen 0.5 ms early; the line then seems free for a
  whole period while the next frame is due in half a millisecond.  So a frame counts
  as early only by a sliver (``EARLY``): anything else is the frame before, late.
  Getting a truly early frame wrong this way only costs one pause.
* **Letting late frames move the phase.**  The phase is the front of the densest
  cluster the recent frames form, modulo the period.  Frames seen late, alone or in a
  run, land apart from it and move nothing; a lasting change (a sensor whose clock
  runs a little slow, an adapter that holds bytes longer) moves the whole cluster, and
  the phase with it within a window.

The period is the configured one: the sensor's clock is a crystal's, a few parts in
ten thousand at worst, which the window (``WINDOW`` frames) follows.  A constant delay
longer than a period (an FTDI adapter at its default 16 ms latency timer, at 100 Hz)
cannot be told from a phase at all: set the adapter to low latency
(docs/bus-master.md).

Sans-IO: time is an argument.
"""

from __future__ import annotations

import math
from collections import deque

WINDOW = 64  # recent frames the phase is estimated from
CLUSTER = 4  # frames at the cluster's front: the phase is their middle one
WIDTH = 0.05  # the part of a period the on-time frames are looked for in
EARLY = 0.02  # the part of a period a frame may be seen before its end in phase


class StreamPhase:
    """The phase of one stream of frames every ``period`` seconds."""

    def __init__(self, period: float) -> None:
        self.period = period
        self.anchor: float | None = None  # a frame end in phase (None: nothing seen yet)
        self._seen: deque[float] = deque(maxlen=WINDOW)

    def seen(self, at: float) -> None:
        """A frame was seen (its last byte came in) at ``at``."""
        self._seen.append(at)
        if self.anchor is None:
            self.anchor = at
            return
        half = self.period / 2
        offsets = sorted((a - self.anchor + half) % self.period - half for a in self._seen)
        self.anchor += self._front(offsets)
        # Keep the anchor near now: it is only meaningful modulo the period, and a
        # float far from the times it is compared with loses precision.
        self.anchor += math.floor((at - self.anchor) / self.period) * self.period

    def _front(self, offsets: list[float]) -> float:
        """The front of the cluster in sorted ``offsets`` (each within half a period of
        the anchor).  The cluster is the densest ``WIDTH`` of them: the frames seen on
        time, or as near it as this machine manages.  Frames seen late by more than
        half a period land *before* it on the circle, and a few of them together must
        not pass for the front, so the densest span wins, not the first.  Its front is
        the middle of its first ``CLUSTER + 1``: one or two stragglers just before the
        on-time frames do not move it either."""
        width = WIDTH * self.period
        best, best_count, j = 0, 0, 0
        for i, offset in enumerate(offsets):
            while j < len(offsets) and offsets[j] <= offset + width:
                j += 1
            if j - i > best_count:
                best, best_count = i, j - i
        if best_count <= CLUSTER:
            return offsets[best]  # too few frames yet for a cluster: its earliest
        return offsets[best + CLUSTER // 2]

    def end_of(self, at: float) -> float:
        """The true end, in phase, of a frame seen at ``at``: at or before ``at``, or a
        sliver (``EARLY``) after it."""
        if self.anchor is None:
            return at
        return self.anchor + math.floor((at - self.anchor) / self.period + EARLY) * self.period
