"""A capture played back: each line of it on a pseudo-terminal (docs/simulator.md,
"Replay"), so a second gateway sees what the first saw.

``frames.jsonl`` has, per line, every request the gateway wrote (``tx``), the bytes
that came back while it waited for an answer (``rx``: the answer, garbage and all)
and the bytes nobody asked for (``rx-unasked``: stream frames, late answers, noise).
Played back:

* each request is answered with the recorded answer to the same bytes, the next one
  in recorded order, each piece at its recorded delay after the request; a request
  the capture does not hold (or holds no more of) gets no answer;
* the unasked bytes go at their recorded times.  The gateway under test keeps its own
  time, so the replay's clock follows it: at each answered request the recording's
  time is set to that request's (its lateness or earliness shifts what follows, not
  what was heard).

The line's baud rate is the recording's (a pty carries bytes, not bits).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import threading
import tty
import zipfile
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

TX, RX, RX_UNASKED = "tx", "rx", "rx-unasked"


@dataclass(frozen=True, slots=True)
class Answer:
    """The recorded answer to one request: when the request went, and the pieces that
    came back, each with its delay after it (none: it was not answered)."""

    at: float
    pieces: tuple[tuple[float, bytes], ...]


@dataclass(frozen=True, slots=True)
class Recording:
    """One line of a capture."""

    bus: str
    answers: dict[bytes, tuple[Answer, ...]]  # by request, in recorded order
    unasked: tuple[tuple[float, bytes], ...]  # (recorded time, bytes), in order
    start: float  # the first frame's recorded time


def load(path: str | Path) -> list[Recording]:
    """The lines of a capture ZIP, in ``meta.json``'s order.  Raises ``ValueError``
    naming what is wrong with a file that is not a capture, ``OSError`` for one that
    cannot be read."""
    try:
        with zipfile.ZipFile(path) as archive:
            meta = json.loads(archive.read("meta.json"))
            lines = archive.read("frames.jsonl").decode("utf-8").splitlines()
        frames: dict[str, list[tuple[float, str, bytes]]] = {
            bus["name"]: [] for bus in meta["buses"]}
        for line in lines:
            entry = json.loads(line)
            frames.setdefault(entry["bus"], []).append(
                (float(entry["t"]), entry["dir"], bytes.fromhex(entry["hex"])))
    except (KeyError, TypeError, ValueError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{path} is not a capture of imu-gateway (a ZIP with meta.json "
                         f"and frames.jsonl): {exc}") from None
    return [_recording(bus, entries) for bus, entries in frames.items()]


def _recording(bus: str, entries: list[tuple[float, str, bytes]]) -> Recording:
    answers: dict[bytes, list[Answer]] = {}
    unasked: list[tuple[float, bytes]] = []
    request: tuple[float, bytes, list[tuple[float, bytes]]] | None = None

    def close() -> None:
        if request is not None:
            at, data, pieces = request
            answers.setdefault(data, []).append(Answer(at, tuple(pieces)))

    for t, direction, data in sorted(entries, key=lambda e: e[0]):
        if direction == TX:
            close()
            request = (t, data, [])
        elif direction == RX and request is not None:
            request[2].append((t - request[0], data))
        else:  # unasked, or an answer to a request before the window
            unasked.append((t, data))
    close()
    start = min((e[0] for e in entries), default=0.0)
    return Recording(bus, {k: tuple(v) for k, v in answers.items()}, tuple(unasked), start)


@dataclass(slots=True)
class ReplayStats:
    answered: int = 0
    unanswered: int = 0  # requests the capture did not hold (or no more of)
    unasked_sent: int = 0


@dataclass(slots=True)
class _Line:
    recording: Recording
    master: int
    slave: int  # kept open: a pty whose slave side nobody holds reads as EIO
    path: str
    answers: dict[bytes, deque[Answer]]
    unasked: deque[tuple[float, bytes]]
    heard: bytearray = field(default_factory=bytearray)
    offset: float = 0.0  # the replay's time less the recording's
    timer: asyncio.TimerHandle | None = None
    stats: ReplayStats = field(default_factory=ReplayStats)


class Replay:
    """Every line of a capture on its own pseudo-terminal, played on one event loop."""

    def __init__(self, recordings: list[Recording], link: str | None = None) -> None:
        self.recordings = recordings
        self.link = link
        self.lines: list[_Line] = []
        self._links: list[str] = []

    def link_of(self, bus: str) -> str | None:
        """``--link PATH``: the one line's, or ``PATH.<bus>`` for each of several."""
        if not self.link:
            return None
        return self.link if len(self.recordings) == 1 else f"{self.link}.{bus}"

    def open(self) -> dict[str, str]:
        """A pty per line; their paths by bus.  Raises ``OSError`` for a link that
        cannot be made (a file that is not a symlink is never replaced)."""
        for recording in self.recordings:
            master, slave = os.openpty()
            tty.setraw(slave)
            os.set_blocking(master, False)
            path = os.ttyname(slave)
            line = _Line(recording, master, slave, path,
                         {k: deque(v) for k, v in recording.answers.items()},
                         deque(recording.unasked))
            self.lines.append(line)
            link = self.link_of(recording.bus)
            if link:
                if os.path.lexists(link) and not os.path.islink(link):
                    raise FileExistsError(f"{link} exists and is not a symlink; not "
                                          "replacing it")
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(link)
                os.symlink(path, link)
                self._links.append(link)
        return {line.recording.bus: line.path for line in self.lines}

    def close(self) -> None:
        for line in self.lines:
            if line.timer is not None:
                line.timer.cancel()
            for fd in (line.master, line.slave):
                with contextlib.suppress(OSError):
                    os.close(fd)
        for link in self._links:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(link)
        self.lines, self._links = [], []

    async def serve(self, stop: asyncio.Event) -> None:
        loop = asyncio.get_running_loop()
        now = loop.time()
        for line in self.lines:
            line.offset = now - line.recording.start
            loop.add_reader(line.master, self._readable, line)
            self._arm(line)
        try:
            await stop.wait()
        finally:
            for line in self.lines:
                loop.remove_reader(line.master)

    # ------------------------------------------------------------ playing

    def _readable(self, line: _Line) -> None:
        try:
            data = os.read(line.master, 4096)
        except (BlockingIOError, OSError):
            return
        line.heard += data
        while line.heard:
            request = self._request(line)
            if request is None:
                return  # the start of a request: the rest is on its way
            self._answer(line, request)

    def _request(self, line: _Line) -> bytes | None:
        """The request ``heard`` starts with (b"": none the capture knows, dropped)."""
        heard = bytes(line.heard)
        for request in line.answers:
            if heard.startswith(request):
                del line.heard[:len(request)]
                return request
        if any(request.startswith(heard) for request in line.answers):
            return None
        line.heard.clear()
        line.stats.unanswered += 1
        return b""

    def _answer(self, line: _Line, request: bytes) -> None:
        queue = line.answers.get(request)
        if not queue:
            if request:
                line.stats.unanswered += 1
            return
        answer = queue.popleft()
        line.stats.answered += 1
        loop = asyncio.get_running_loop()
        now = loop.time()
        line.offset = now - answer.at  # the recording's clock follows the gateway's
        for delay, piece in answer.pieces:
            loop.call_at(now + delay, self._write, line, piece)
        self._arm(line)

    def _arm(self, line: _Line) -> None:
        """A timer for the next unasked bytes, at their recorded time."""
        if line.timer is not None:
            line.timer.cancel()
            line.timer = None
        if line.unasked:
            loop = asyncio.get_running_loop()
            line.timer = loop.call_at(line.unasked[0][0] + line.offset, self._unasked, line)

    def _unasked(self, line: _Line) -> None:
        line.timer = None
        now = asyncio.get_running_loop().time()
        while line.unasked and line.unasked[0][0] + line.offset <= now + 0.0005:
            self._write(line, line.unasked.popleft()[1])
            line.stats.unasked_sent += 1
        self._arm(line)

    @staticmethod
    def _write(line: _Line, data: bytes) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(line.master, data)

    def summary(self) -> dict[str, Any]:
        return {line.recording.bus: {"answered": line.stats.answered,
                                     "unanswered": line.stats.unanswered,
                                     "unasked_sent": line.stats.unasked_sent,
                                     "answers_left": sum(map(len, line.answers.values()))}
                for line in self.lines}


class ReplayThread:
    """A ``Replay`` on its own event loop in a background thread (tests)."""

    def __init__(self, path: str | Path) -> None:
        self.replay = Replay(load(path))
        self.paths = self.replay.open()
        self._loop = asyncio.new_event_loop()
        self._stop = asyncio.Event()
        self._thread = threading.Thread(target=self._run, name="replay", daemon=True)

    def _run(self) -> None:
        self._loop.run_until_complete(self.replay.serve(self._stop))

    def __enter__(self) -> ReplayThread:
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)
        self._loop.close()
        self.replay.close()


@contextlib.contextmanager
def replaying(path: str | Path) -> Iterator[ReplayThread]:
    with ReplayThread(path) as replay:
        yield replay
