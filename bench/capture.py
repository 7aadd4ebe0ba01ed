"""The memory of event capture's rings (docs/benchmarks.md, "The capture's ring").

* **A sensor's ring**: 10 s of samples at 100 Hz (1000 rows), for each series (an AH
  measures 16 fields, an IMU 6), each row as the cache's reading event makes it.
* **A line's frame ring**: 10 s of a line polled at 100 Hz (a 5-byte request and a
  57-byte answer each, native AH's all-data read), 2000 entries.

Measured with ``tracemalloc``: what the ring holds once the rows are in, every snapshot
they were made from released.  A sensor's ring has one row more than its samples: the
status change of its first reading (offline to ok) is a row too.

Run: ``.venv/bin/python bench/capture.py [--hz 100] [--seconds 10]``.
"""

from __future__ import annotations

import argparse
import gc
import time
import tracemalloc
from collections import deque

from imu_gateway.cache import Cache, EventKind, Snapshot
from imu_gateway.capture.ring import SensorRing, series_fields
from imu_gateway.model import Angles, Quaternion, Reading, Series, Vector3

#: a sample with every group (an AH's): the values do not change the size of a row
SAMPLE = Reading(Angles(1.25, -3.5, 270.0), Vector3(0.01, -0.02, 0.99), Vector3(0.5, 0.1, -0.3),
                 Vector3(0.2, 0.05, 0.4), Quaternion(0.99, 0.01, 0.02, 0.03))


def ring_bytes(series: Series, hz: float, seconds: float) -> tuple[int, int]:
    """The ring's bytes once ``hz × seconds`` samples are in, and its rows."""
    rows = int(hz * seconds)
    ring = SensorRing(series_fields(series), seconds + 1)  # (all rows kept: no trimming)
    cache = Cache([("s", 1000.0)])

    def keep(kind: EventKind, snap: Snapshot) -> None:
        row = ring.pack(kind, snap)
        if row is not None:
            ring.add(row)

    cache.subscribe(keep)
    gc.collect()
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for _ in range(rows):
        cache.publish("s", SAMPLE)
    gc.collect()
    # (the cache keeps its latest sample: a timestamp, some bytes; SAMPLE is shared)
    held = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    return held, len(ring.rows)


def frame_ring_bytes(hz: float, seconds: float) -> tuple[int, int]:
    entries = int(2 * hz * seconds)
    ring: deque[tuple[float, str, bytes]] = deque(maxlen=entries)
    request, answer = bytes(5), bytes(57)
    gc.collect()
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for i in range(entries // 2):
        t = time.monotonic()
        ring.append((t, "tx", bytes(request)))  # (a fresh object each, as from the port)
        ring.append((t + 0.001, "rx" if i % 7 else "rx-unasked", bytes(answer)))
    held = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    return held, len(ring)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--hz", type=float, default=100.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    print(f"{args.seconds:g} s at {args.hz:g} Hz")
    for series in (Series.AH, Series.VG, Series.IMU):
        held, rows = ring_bytes(series, args.hz, args.seconds)
        fields = len(series_fields(series))
        print(f"sensor ring, {series.name:3} ({fields:2} fields): {rows} rows, "
              f"{held / 1024:7.1f} KiB ({held / max(rows, 1):5.0f} B/row)")
    held, entries = frame_ring_bytes(args.hz, args.seconds)
    print(f"frame ring, one line polled at {args.hz:g} Hz: {entries} entries, "
          f"{held / 1024:7.1f} KiB ({held / max(entries, 1):5.0f} B/entry)")


if __name__ == "__main__":
    main()
