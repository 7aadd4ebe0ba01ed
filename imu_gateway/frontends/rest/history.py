"""The recent past of every sensor, for the dashboard's trends
(``GET /api/v1/sensors/{name}/history``).

A ring of one-second buckets per sensor, ``KEEP_S`` of them: for each measured field,
its lowest, highest and last value in that second.  So a 100 Hz sensor costs the same
as a 1 Hz one (one bucket a second, a few hundred bytes), a trend shows the spikes a
plain sample would hide, and ten minutes of twenty sensors take a few MB.  It is fed
by the cache's reading events, on the main loop; it never touches a bus.
"""

from __future__ import annotations

import math
from array import array
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from ...cache import EventKind, Snapshot
from ...normalise import MEASURED_FIELDS, field_values
from ..common import GatewayLike

BUCKET_S = 1
KEEP_S = 600  # ten minutes


@dataclass(slots=True)
class _Bucket:
    start: int  # epoch seconds
    # lowest, highest and last of each field, in the sensor's field order
    values: array[float]


class History:
    """Every sensor's last ``KEEP_S`` seconds, a bucket a second."""

    def __init__(self, gateway: GatewayLike) -> None:
        self.fields = {name: MEASURED_FIELDS[sensor.series]
                       for name, sensor in gateway.sensors.items()}
        self._rings: dict[str, deque[_Bucket]] = {
            name: deque(maxlen=KEEP_S // BUCKET_S) for name in gateway.sensors}

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.READING and snap.reading is not None and snap.timestamp:
            values = field_values(snap.reading)
            self.add(snap.name, snap.timestamp.timestamp(),
                     [values.get(f, math.nan) for f in self.fields[snap.name]])

    def add(self, name: str, at: float, values: Sequence[float]) -> None:
        ring = self._rings[name]
        start = int(at // BUCKET_S * BUCKET_S)
        n = len(values)
        if ring and ring[-1].start == start:
            b = ring[-1].values
            for i, v in enumerate(values):
                if math.isfinite(v):  # NaN (a Modbus float register) is no value
                    b[i] = v if math.isnan(b[i]) else min(b[i], v)
                    b[n + i] = v if math.isnan(b[n + i]) else max(b[n + i], v)
                    b[2 * n + i] = v
            return
        if ring and start < ring[-1].start:
            return  # the clock stepped back: the next second takes it up again
        clean = [v if math.isfinite(v) else math.nan for v in values]
        ring.append(_Bucket(start, array("d", clean * 3)))

    def query(self, name: str, seconds: float, now: float) -> dict[str, Any]:
        """The buckets of the last ``seconds`` up to ``now`` (epoch seconds), as
        columns: ``t`` (each bucket's start) and, per field, ``min``, ``max``, ``last``
        (``None`` where a second had no finite value)."""
        fields = self.fields[name]
        n = len(fields)
        picked = [b for b in self._rings[name] if b.start > now - seconds - BUCKET_S]
        columns: dict[str, dict[str, list[float | None]]] = {
            f: {"min": [], "max": [], "last": []} for f in fields}
        for b in picked:
            for i, f in enumerate(fields):
                for j, key in enumerate(("min", "max", "last")):
                    v = b.values[j * n + i]
                    columns[f][key].append(None if math.isnan(v) else v)
        return {"sensor": name, "seconds": seconds, "bucket_s": BUCKET_S,
                "t": [b.start for b in picked], "fields": columns}
