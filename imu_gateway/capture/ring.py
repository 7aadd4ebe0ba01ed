"""Every sample of every sensor for the last ``pre_s`` seconds, in bounded memory.

A row is packed into one ``bytes`` by ``struct`` (times, seq, status, errors, then one
double per field of the sensor's series): about a third of what a tuple of Python
floats takes, and a tenth of a ``Snapshot`` with its ``Reading``.  ``bench/capture.py``
measures it (docs/benchmarks.md, "The capture's ring").

The times of a row (wall-clock seconds since the epoch):

* **wire**: when the sample's last byte came in from the line.  The bus master notes
  that moment, and the cache makes it the snapshot's time (``Snapshot.timestamp``).
* **receive**: when the main loop put it in the cache (the capture hears it then):
  the hand-over from the bus thread is in between, up to 0.1 s (0.25 at most) when
  nobody pushes readings out (``bus.runner``).

A change of status (``stale``, ``offline``) is a row too, with no wire time and no
values: the capture shows when a sensor stopped answering.
"""

from __future__ import annotations

import math
import struct
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from ..cache import EventKind, Snapshot, Status
from ..derived import values_of
from ..model import CAPABILITIES, VALUE_GROUPS, Series

#: the rows a sensor's ring holds at most, whatever its rate (1000 Hz for ``pre_s``)
MAX_RATE_HZ = 1000
_HEAD = struct.Struct("<ddIIB")  # wire, receive, seq, errors, kind and status
_TIME = struct.Struct("<d")  # one time of a row: its receive time, at 8 (trimmed by it)
_STATUSES = tuple(Status)
_READING, _STATUS = 0, 1
KINDS = ("reading", "status")


def series_fields(series: Series) -> tuple[str, ...]:
    """The fields a series measures, in the value-group table's order."""
    groups = CAPABILITIES[series].groups
    return tuple(name for group, spec in VALUE_GROUPS.items() if group in groups
                 for name in spec.fields)


@dataclass(frozen=True, slots=True)
class Row:
    """One row of a capture's CSV, unpacked."""

    kind: str  # "reading" or "status"
    wire: float | None  # a status row has none
    receive: float
    seq: int
    status: str
    errors: int
    values: tuple[float | None, ...]  # None: absent (or not a number)


class SensorRing:
    """One sensor's rows, the newest first out, trimmed to ``keep`` seconds."""

    def __init__(self, fields: Sequence[str], keep: float, rate_hz: float = MAX_RATE_HZ) -> None:
        self.fields = tuple(fields)
        self.keep = keep
        self._row = struct.Struct(_HEAD.format + "d" * len(self.fields))
        self.rows: deque[bytes] = deque(maxlen=max(16, math.ceil(keep * rate_hz)))

    def pack(self, kind: EventKind, snap: Snapshot) -> bytes | None:
        """The snapshot as a row (``None``: an event the capture does not keep)."""
        if snap.timestamp is None:
            return None
        receive = time.time()
        status = _STATUSES.index(snap.status)
        if kind is EventKind.READING:
            values = values_of(snap)
            wire = snap.timestamp.timestamp()
            return self._row.pack(wire, receive, snap.seq, snap.errors, status,
                                  *(values.get(f, math.nan) for f in self.fields))
        if kind is EventKind.STATUS:
            return self._row.pack(math.nan, receive, snap.seq, snap.errors,
                                  _STATUS << 4 | status, *(math.nan,) * len(self.fields))
        return None

    def resized(self, keep: float, rate_hz: float = MAX_RATE_HZ) -> SensorRing:
        """A ring of ``keep`` seconds with this one's newest rows that fit (a reload)."""
        ring = SensorRing(self.fields, keep, rate_hz)
        ring.rows.extend(self.rows)  # (the deque's length keeps the newest)
        if ring.rows:
            newest = _TIME.unpack_from(ring.rows[-1], 8)[0]
            while _TIME.unpack_from(ring.rows[0], 8)[0] < newest - keep:
                ring.rows.popleft()
        return ring

    def add(self, row: bytes) -> None:
        self.rows.append(row)
        newest = _TIME.unpack_from(row, 8)[0]  # the receive time
        while _TIME.unpack_from(self.rows[0], 8)[0] < newest - self.keep:
            self.rows.popleft()

    def since(self, start: float) -> list[bytes]:
        """The rows received at ``start`` or later (a copy: the ring goes on): every
        reading that came off the wire then or later too, as it is received after."""
        return [row for row in self.rows if _TIME.unpack_from(row, 8)[0] >= start]

    def unpack(self, rows: Sequence[bytes]) -> Iterator[Row]:
        for raw in rows:
            wire, receive, seq, errors, code, *values = self._row.unpack(raw)
            yield Row(KINDS[code >> 4], None if math.isnan(wire) else wire, receive, seq,
                      _STATUSES[code & 0xF].value, errors,
                      tuple(None if not math.isfinite(v) else v for v in values))
