"""What the front ends make of a sample, made once per sample however many of them
(and however many of their clients) use it.

The cache hands every listener the same ``Snapshot`` object for one event, and a
snapshot never changes: so what is derived from it is kept for the snapshot last
asked about.  The MQTT state, Home Assistant's state and the live stream's event
share one encoding of the reading JSON; the history, OPC UA, Modbus TCP, Sparkplug
and MQTT share one dict of field values (docs/benchmarks.md, "CPU per sample in the
front ends", for what each copy cost).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any, Generic, TypeVar

from .cache import Snapshot
from .normalise import field_values

T = TypeVar("T")


#: (one for all: ``json.dumps`` with options makes an encoder per call, 0.6 of its
#: 4.6 µs for a reading; ``encode`` keeps no state between calls)
_ENCODER = json.JSONEncoder(separators=(",", ":"), ensure_ascii=False, allow_nan=False)


def json_bytes(value: Any) -> bytes:
    """Compact JSON as the front ends send it.  ``allow_nan=False``: the reading JSON
    has no NaN (``Reading.to_json_groups`` makes it null), and nothing else should."""
    return _ENCODER.encode(value).encode()


class _OncePerSnapshot(Generic[T]):
    """``make(snapshot)``, kept for the snapshot last asked about.  The pair is
    replaced in one assignment, so a caller on another thread never gets one
    snapshot's value for another.  The value is shared: never change it."""

    def __init__(self, make: Callable[[Snapshot], T]) -> None:
        self._make = make
        self._last: tuple[Snapshot | None, T | None] = (None, None)

    def __call__(self, snap: Snapshot) -> T:
        last_snap, value = self._last
        if last_snap is not snap or value is None:
            value = self._make(snap)
            self._last = (snap, value)  # (holding the snapshot: its id is not reused)
        return value


#: The reading JSON (``Snapshot.to_json``) as compact bytes.
reading_json: Callable[[Snapshot], bytes] = _OncePerSnapshot(
    lambda snap: json_bytes(snap.to_json()))

#: The sample's measured values by field name (empty before the first reading).
values_of: Callable[[Snapshot], Mapping[str, float]] = _OncePerSnapshot(
    lambda snap: field_values(snap.reading) if snap.reading is not None else {})
