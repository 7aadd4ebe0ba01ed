"""The alarm journal's file (``alarm_journal``): each transition appended as a JSON
line by a thread of its own, and the last ``JOURNAL_SIZE`` read back at start.

A write never runs on the event loop, where the samples are evaluated: a slow disk
would hold every front end.  A write that fails (a full or read-only disk) is counted
and warned about once, until a write works again; it never raises into the gateway.
"""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
from collections import deque

from .alarms import JOURNAL_SIZE, Transition

log = logging.getLogger("imu_gateway.alarms")

_STOP = None  # what ``close`` queues


class JournalFile:
    """Appends transitions to ``path``, one JSON object a line, in order."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._written = 0  # transitions written
        self._errors = 0  # transitions that could not be written
        self._carried = (0, 0)  # a previous file's counts (a reload: the counters go on)
        self._queue: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._failing = False

    @property
    def written(self) -> int:
        return self._carried[0] + self._written

    @property
    def errors(self) -> int:
        return self._carried[1] + self._errors

    def follow(self, old: JournalFile) -> None:
        """Count on from ``old``'s counts (a reload; ``old`` closed)."""
        self._carried = (old.written, old.errors)

    def is_empty(self) -> bool:
        """No line in the file yet (missing, or empty)."""
        try:
            return os.path.getsize(self.path) == 0
        except OSError:
            return True

    def read(self) -> list[Transition]:
        """The file's last ``JOURNAL_SIZE`` transitions, oldest first: none when it is
        missing, or not a regular file (``/dev/full`` would be read for ever).  A line
        that is not a transition is skipped, with one warning for them all."""
        if not os.path.isfile(self.path):
            return []
        try:
            with open(self.path, "rb") as lines:
                tail = deque(lines, maxlen=JOURNAL_SIZE)
        except OSError as exc:
            log.warning("alarm journal %s: cannot read it (%s); the alarms start normal",
                        self.path, exc.strerror or exc)
            return []
        out, bad = [], 0
        for line in tail:
            try:
                out.append(Transition.from_json(json.loads(line)))
            except (ValueError, KeyError, TypeError):
                bad += 1
        if bad:
            log.warning("alarm journal %s: skipped %d line(s) that are not transitions",
                        self.path, bad)
        return out

    def append(self, change: Transition) -> None:
        """Queue one transition for the writer (started at the first)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="alarm journal",
                                            daemon=True)
            self._thread.start()
        line = json.dumps(change.to_json(), separators=(",", ":"), allow_nan=False)
        self._queue.put(line.encode() + b"\n")

    def close(self, timeout: float = 5.0) -> None:
        """Write what is queued, then stop the writer (blocks up to ``timeout``)."""
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join(timeout)
            self._thread = None

    def _run(self) -> None:
        while True:
            batch = [self._queue.get()]
            while not self._queue.empty():  # what came meanwhile goes in one write
                batch.append(self._queue.get())
            lines = [b for b in batch if b is not _STOP]
            if lines:
                self._write(lines)
            if _STOP in batch:
                return

    def _write(self, lines: list[bytes]) -> None:
        try:
            with open(self.path, "ab") as out:  # opened per batch: a rotated file is fine
                out.write(b"".join(lines))
                out.flush()
                os.fsync(out.fileno())
        except OSError as exc:
            self._errors += len(lines)
            if not self._failing:
                self._failing = True
                log.warning("alarm journal %s: cannot write (%s); transitions are kept "
                            "in memory only, and counted "
                            "(imu_gateway_alarm_journal_errors_total) until it works again",
                            self.path, exc.strerror or exc)
            return
        self._written += len(lines)
        if self._failing:
            self._failing = False
            log.info("alarm journal %s: writing again", self.path)
