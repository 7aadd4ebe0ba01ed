"""The recent past of every sensor: the last ``KEEP_S`` seconds, one bucket a second.

The gateway keeps one ``History`` (``app.Gateway.history``), fed by the cache's
reading events on the main loop; the front ends only read it: REST's trends
(``GET /api/v1/sensors/{name}/history``) and OPC UA's HistoryRead.  It never touches
a bus.

For each measured and derived field a second keeps its lowest, highest and last finite value, the
sum and the count of its finite values (so a mean over whole seconds is exact), and
the second keeps the wire time of its last sample (``Snapshot.timestamp``: raw history
carries the sample's own time).  So a 100 Hz sensor costs the same as a 1 Hz one, and
a trend shows the spikes a plain sample would hide.

A sensor's ring is preallocated (``array``, no object per second): its memory is fixed
from the start, ``History.nbytes`` says how much (about 400 KB for ten minutes of an
AH's 19 fields: 16 measured, 3 derived), and a long run never grows it.  The ring is
indexed by the second itself (slot = second mod ``KEEP_S``), so a second the sensor
was silent is simply absent.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from .cache import EventKind, Snapshot
from .config import SensorConfig
from .derived import values_of
from .normalise import MEASURED_FIELDS

BUCKET_S = 1  # the buckets are whole seconds (the ring's index is the second)
KEEP_S = 600  # ten minutes
_COUNT_MAX = 0xFFFF  # (an unsigned short; no sensor gives 65535 samples a second)
_STATS = 4  # per field and second: lowest, highest, last, sum (then the count apart)


class _HasSensors(Protocol):
    @property
    def sensors(self) -> Mapping[str, SensorConfig]: ...


@dataclass(frozen=True, slots=True)
class Second:
    """One kept second of one field (only seconds that had a finite value of it)."""

    start: int  # epoch seconds: the bucket is [start, start + 1)
    at: float  # wire time (epoch seconds) of the second's last sample
    low: float
    high: float
    last: float  # the last finite value
    total: float  # the sum of the second's finite values
    count: int  # how many


class _Ring:
    """One sensor's seconds, preallocated: slot = second mod ``KEEP_S``; a slot holds
    the second ``starts[slot]`` (-1: never used).

    The second being filled keeps its samples as they came, and is folded into its
    slot when the next second starts or something reads the ring: a sample costs an
    append, not a dozen array updates per field (measured: 16 of the 18 µs a reading
    cost the cache, warm; more on a busy loop)."""

    def __init__(self, n: int) -> None:
        self.n = n
        self._clear()

    def _clear(self) -> None:
        n = self.n
        self.newest = -1  # the latest second kept
        self.starts = array("q", [-1]) * KEEP_S
        self.stamps = array("d", [math.nan]) * KEEP_S
        self.stats = array("d", [math.nan]) * (KEEP_S * _STATS * n)
        self.counts = array("H", [0]) * (KEEP_S * n)
        self._rows: list[Sequence[float]] = []  # the newest second's samples
        self._folded = 0  # how many of them its slot holds

    @property
    def nbytes(self) -> int:
        return sum(a.itemsize * len(a) for a in (self.starts, self.stamps, self.stats,
                                                 self.counts))

    def add(self, at: float, values: Sequence[float]) -> None:
        second = math.floor(at)
        if second == self.newest:
            self._rows.append(values)
            self.stamps[second % KEEP_S] = at
            return
        self.fold()
        if second < self.newest - KEEP_S:
            self._clear()  # the clock went far back: start again
        elif second < self.newest:
            return  # a small step back of the clock: the next new second takes it up
        slot = second % KEEP_S
        self.starts[slot] = second  # (the slot's old second goes)
        self.newest = second
        self.stamps[slot] = at
        self._rows, self._folded = [values], 0

    def fold(self) -> None:
        """The newest second's samples into its slot: per field, the lowest, highest
        and last finite value, their sum and count (a value that is not finite, NaN
        from a Modbus float register, is no value)."""
        rows = self._rows
        if self._folded == len(rows):
            return
        n, slot = self.n, self.newest % KEEP_S
        base, stats, counts = slot * _STATS * n, self.stats, self.counts
        isfinite = math.isfinite
        for i, column in enumerate(zip(*rows, strict=True)):
            good = [v for v in column if isfinite(v)]
            kept = good[:_COUNT_MAX]
            stats[base + i] = min(good) if good else math.nan
            stats[base + n + i] = max(good) if good else math.nan
            stats[base + 2 * n + i] = good[-1] if good else math.nan
            stats[base + 3 * n + i] = sum(kept, 0.0)
            counts[slot * n + i] = len(kept)
        self._folded = len(rows)

    def slots(self) -> Iterator[tuple[int, int]]:
        """(second, slot) of every kept second, oldest first."""
        self.fold()
        return self._slots()

    def _slots(self) -> Iterator[tuple[int, int]]:
        for second in range(self.newest - KEEP_S + 1, self.newest + 1):
            slot = second % KEEP_S
            if second >= 0 and self.starts[slot] == second:
                yield second, slot

    def second(self, second: int, slot: int, i: int) -> Second | None:
        count = self.counts[slot * self.n + i]
        if count == 0:
            return None
        base, n = slot * _STATS * self.n, self.n
        return Second(second, self.stamps[slot], self.stats[base + i], self.stats[base + n + i],
                      self.stats[base + 2 * n + i], self.stats[base + 3 * n + i], count)


class History:
    """Every sensor's last ``KEEP_S`` seconds, a bucket a second."""

    def __init__(self, gateway: _HasSensors) -> None:
        self.fields = {name: MEASURED_FIELDS[sensor.series]
                       for name, sensor in gateway.sensors.items()}
        self._rings = {name: _Ring(len(fields)) for name, fields in self.fields.items()}

    def set_sensors(self, gateway: _HasSensors) -> None:
        """A reload: a sensor kept with the same fields keeps its past; a new one (or
        one of another series) starts empty; those gone are forgotten."""
        fields = {name: MEASURED_FIELDS[sensor.series]
                  for name, sensor in gateway.sensors.items()}
        self._rings = {name: self._rings[name] if self.fields.get(name) == f
                       else _Ring(len(f)) for name, f in fields.items()}
        self.fields = fields

    @property
    def nbytes(self) -> int:
        """The memory the rings hold (fixed from the start)."""
        return sum(ring.nbytes for ring in self._rings.values())

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.READING and snap.reading is not None and snap.timestamp:
            values = values_of(snap)
            self.add(snap.name, snap.timestamp.timestamp(),
                     [values.get(f, math.nan) for f in self.fields[snap.name]])

    def add(self, name: str, at: float, values: Sequence[float]) -> None:
        """A sample of sensor ``name`` taken at wire time ``at`` (epoch seconds), its
        values in ``fields[name]``'s order.  A sample older than the newest second is
        dropped (the clock stepped back), unless it is more than ``KEEP_S`` older: then
        the clock went far back and the ring starts again."""
        self._rings[name].add(at, values)

    def seconds(self, name: str, field: str) -> list[Second]:
        """The kept seconds with a value of ``field``, oldest first."""
        ring = self._rings[name]
        i = self.fields[name].index(field)
        return [s for second, slot in ring.slots()
                if (s := ring.second(second, slot, i)) is not None]

    def query(self, name: str, seconds: float, now: float) -> dict[str, Any]:
        """The buckets of the last ``seconds`` up to ``now`` (epoch seconds), as
        columns: ``t`` (each bucket's start) and, per field, ``min``, ``max``, ``last``
        (``None`` where a second had no finite value)."""
        fields, ring = self.fields[name], self._rings[name]
        n = len(fields)
        picked = [(second, slot) for second, slot in ring.slots()
                  if second > now - seconds - BUCKET_S]
        columns: dict[str, dict[str, list[float | None]]] = {
            f: {"min": [], "max": [], "last": []} for f in fields}
        for _, slot in picked:
            base = slot * _STATS * n
            for i, f in enumerate(fields):
                for j, key in enumerate(("min", "max", "last")):
                    v = ring.stats[base + j * n + i]
                    columns[f][key].append(None if math.isnan(v) else v)
        return {"sensor": name, "seconds": seconds, "bucket_s": BUCKET_S,
                "t": [second for second, _ in picked], "fields": columns}
