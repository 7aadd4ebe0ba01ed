"""A capture on disk: one ZIP (a CSV per sensor, ``frames.jsonl``, ``meta.json``), its
id, the folder's index and its retention.  Everything here does file I/O and runs on a
worker thread, never on the event loop."""

from __future__ import annotations

import csv
import io
import json
import os
import re
import zipfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from .ring import Row

#: A capture's id: its trigger's UTC time to the millisecond, and a number when two
#: fall in one millisecond.  Nothing else is an id, so no id names a path outside
#: the folder (``../``, ``/``, a dot file).
ID = re.compile(r"[0-9]{8}T[0-9]{9}Z(-[0-9]{1,4})?")
SUFFIX = ".zip"
CSV_HEAD = ("kind", "wire_time", "wire_s", "receive_time", "receive_s", "seq", "status",
            "errors")


def iso(seconds: float) -> str:
    """``2026-11-22T03:40:00.123456Z``: UTC, microseconds (Excel and pandas read it)."""
    return datetime.fromtimestamp(seconds, UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def new_id(at: float, taken: Iterable[str]) -> str:
    """``20261122T034000123Z`` (the trigger's UTC time), or with ``-2``, ``-3``, …"""
    stamp = datetime.fromtimestamp(at, UTC)
    base = stamp.strftime("%Y%m%dT%H%M%S") + f"{stamp.microsecond // 1000:03d}Z"
    used = set(taken)
    if base not in used:
        return base
    return next(f"{base}-{n}" for n in range(2, 10000) if f"{base}-{n}" not in used)


@dataclass(frozen=True, slots=True)
class CaptureInfo:
    """A capture as the list shows it (REST's ``GET /api/v1/captures``, MQTT's announce)."""

    id: str
    trigger: str  # "manual", "alarm", …
    alarm: str | None  # the alarm that triggered it (``sensor/alarm``), if one did
    at: float  # the trigger's time, seconds since the epoch
    size: int  # bytes

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "trigger": self.trigger, "alarm": self.alarm,
                "time": iso(self.at), "size": self.size}


@dataclass(frozen=True, slots=True)
class SensorRows:
    """A sensor's part of a capture: its fields and rows."""

    name: str
    fields: tuple[str, ...]
    rows: tuple[Row, ...]


def sensor_csv(part: SensorRows) -> str:
    """Header row, then one row per sample: ISO times and seconds, one column per
    field, empty for a value absent (or not a number)."""
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow((*CSV_HEAD, *part.fields))
    for row in part.rows:
        writer.writerow((
            row.kind, "" if row.wire is None else iso(row.wire),
            "" if row.wire is None else f"{row.wire:.6f}", iso(row.receive),
            f"{row.receive:.6f}", row.seq, row.status, row.errors,
            *("" if v is None else repr(v) for v in row.values)))
    return out.getvalue()


def frames_jsonl(frames: Mapping[str, Sequence[tuple[float, str, bytes]]]) -> str:
    """One line per frame, every line's in time order: bus, time, direction, hex."""
    lines = [(t, bus, direction, data) for bus, entries in frames.items()
             for t, direction, data in entries]
    lines.sort(key=lambda line: line[0])
    return "".join(json.dumps({"bus": bus, "t": round(t, 6), "time": iso(t), "dir": direction,
                               "hex": data.hex()}) + "\n"
                   for t, bus, direction, data in lines)


def write_capture(folder: Path, info: CaptureInfo, meta: Mapping[str, Any],
                  sensors: Sequence[SensorRows],
                  frames: Mapping[str, Sequence[tuple[float, str, bytes]]]) -> int:
    """Write the ZIP (to a dot file first, then renamed: a list never shows half a
    capture); its size.  Raises ``OSError`` (a full or read-only disk)."""
    folder.mkdir(parents=True, exist_ok=True)
    final = folder / f"{info.id}{SUFFIX}"
    partial = folder / f".{info.id}{SUFFIX}.partial"
    try:
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as archive:
            archive.writestr("meta.json", json.dumps(meta, indent=2) + "\n")
            for part in sensors:
                archive.writestr(f"{part.name}.csv", sensor_csv(part))
            archive.writestr("frames.jsonl", frames_jsonl(frames))
        os.replace(partial, final)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return final.stat().st_size


def read_info(path: Path) -> CaptureInfo | None:
    """A capture's list entry from its ``meta.json`` (``None``: not a capture)."""
    try:
        with zipfile.ZipFile(path) as archive:
            meta = json.loads(archive.read("meta.json"))
        trigger = meta["trigger"]
        return CaptureInfo(path.name.removesuffix(SUFFIX), str(trigger["reason"]),
                           trigger.get("alarm"), float(trigger["t"]), path.stat().st_size)
    except (OSError, KeyError, TypeError, ValueError, zipfile.BadZipFile):
        return None


def scan(folder: Path) -> list[CaptureInfo]:
    """The captures in ``folder``, oldest first (a missing folder has none)."""
    try:
        paths = sorted(p for p in folder.iterdir()
                       if p.name.endswith(SUFFIX) and ID.fullmatch(p.name.removesuffix(SUFFIX)))
    except FileNotFoundError:
        return []
    return [info for p in paths if (info := read_info(p)) is not None]


def retain(folder: Path, kept: Sequence[CaptureInfo], max_files: int,
           max_bytes: float) -> list[CaptureInfo]:
    """Delete the oldest captures until at most ``max_files`` are left and they take at
    most ``max_bytes``; the ones left (the newest is always kept).  Raises ``OSError``."""
    left = sorted(kept, key=lambda info: info.id)
    total = sum(info.size for info in left)
    while len(left) > 1 and (len(left) > max_files or total > max_bytes):
        oldest = left.pop(0)
        (folder / f"{oldest.id}{SUFFIX}").unlink(missing_ok=True)
        total -= oldest.size
    return left
