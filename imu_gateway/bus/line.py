"""The wire as the schedule sees it, sans-IO: the attempt in flight and its deadlines,
when the line is free for the next request, and what is coming in.

The timing rules, each in one place:

* **When a request may go** (``free_at``): never while an attempt is in flight,
  including the time its answer may still come late; after an answer to a retry, not
  before the retry's own answer could have come (the one used may have been the
  attempt before's, late); after a whole answer, once the
  protocol's gap has passed; after noise or half a frame, only once the line has been
  quiet 3.5 characters (at least 1 ms), and a half frame that stopped coming is
  dropped then.  Next to a streaming sensor, only if the exchange fits before its
  next frame (``stream_wait``).
* **Deadlines** (``check``): an attempt's answer is due by its wire time plus the
  sensor's timeout (``timing.AnswerTimer``).  Past that it is *overdue*, but the line
  stays held for another timeout: an answer then is late, and still used.  Only
  after that has the attempt failed.  A timer that fires while the port holds bytes
  not yet received waits for them first: on a busy machine the answer may be in.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from typing import NamedTuple

from ..protocol.exchanges import Exchange, Frame, ProtocolAdapter, char_time
from ..stats import Counters
from .events import Attempt, Job, Request

MIN_QUIET = 0.001  # after noise, the line must have been quiet this long
#: An attempt past its hold with bytes still arriving is waited for this much longer.
ARRIVING_GRACE = 0.05
#: Bytes stuck in the port (a starved reader thread) are waited for at most this long.
STUCK_MAX = 1.0
HEARD_MAX = 512  # bytes of an exchange's answer kept for the trace
#: An exchange that found no place next to a stream for this many periods goes in a
#: pause it fits without the margin for the frames' wobble; after ``LAST_RESORT``
#: times as many, in the next pause it can, fitting or not.
PATIENCE = 10
LAST_RESORT = 4
#: A write that returns later than this after the request was handed out may have put
#: it on the line any time until then (``Line.written``).
SLOW_WRITE = 0.002


class Due(enum.Enum):
    """What ``Line.check`` found of the attempt in flight."""

    NOTHING = 0  # still waiting (or none in flight)
    SENT = 1  # a request nobody answers is out: it is done
    FAILED = 2  # no answer, not even late: the attempt failed


class Place(NamedTuple):
    """Where an exchange goes next to a stream: not before ``at``; written by ``latest``
    or withdrawn; and why there (shown in the frame trace: a collision with a frame is
    then explained by the rule that placed the request; "" with no stream).  ``room``:
    how much later than ``latest`` it would still end before the next frame, if that
    frame came on time (the margin kept for the frames' wobble, where one was kept)."""

    at: float
    latest: float
    why: str
    room: float = 0.0


def stream_margin(period: float) -> float:
    """The room kept beside a stream's frames for their own timing's wobble, and for
    the line to be quiet before a request: what an exchange needs on top of its own
    time to fit a pause of a stream of ``period``."""
    return min(0.02, period / 10) + MIN_QUIET


def stream_wait(now: float, needs: float, last_end: float, period: float,
                frame: float, waited: float = 0.0) -> Place:
    """When an exchange of ``needs`` seconds may start next to a stream whose frames
    take ``frame`` seconds every ``period``, the last one seen ending at ``last_end``
    (``waited``: how long it has waited for a place already); and, when that is now,
    the latest it may still start (the decision is stale after that: a busy machine
    may keep the thread from writing for milliseconds).

    The stream keeps its phase: a frame that was lost (garbled, or dropped by the
    port) does not make the next one come at another time, so the frames are expected
    at ``last_end + k·period``.  A frame due but not seen yet is given half a period
    to arrive (a busy machine, or a sensor's own clock, makes frames late) before it
    is taken for lost and the line is used.

    An exchange that fits no pause, or only one it cannot be on time for (it has to
    start within ``margin`` of a frame's end), goes right after a frame: the least
    harm.  One that has waited ``PATIENCE`` periods (a busy machine that wakes the bus
    late after every frame) goes in a pause it fits without the margin; one that has
    waited ``LAST_RESORT`` times longer takes any pause it is woken in: a busy machine
    must not keep a command from the sensor for ever (the caller passes ``waited`` 0
    for what may wait, a poll).  (Any pause after ``PATIENCE`` alone is the only rule
    that could have sent a request that met a frame in a soak beside CPU burners.)"""
    margin = stream_margin(period)
    k = max(1, math.ceil((now - last_end) / period))
    due = last_end + (k - 1) * period  # the latest frame that should have ended by now
    if k > 1 and now < due + period / 2:
        return Place(due + period / 2, 0.0, "a frame due")  # it may still be coming in
    next_end = due + period
    if now + needs + margin <= next_end - frame:
        return Place(now, next_end - frame - needs - margin, "fits before the next frame",
                     margin)
    slack = period - frame - needs - margin  # how long after a frame's end it still fits
    if waited >= PATIENCE * period and now + needs <= next_end - frame:
        return Place(now, next_end - frame - needs, "waited long: fits without the margin")
    desperate = waited >= LAST_RESORT * PATIENCE * period
    after = period - frame if desperate else margin
    if (slack < margin or desperate) and now - due <= after and k == 1:
        # right after a frame: the least harm (or, having waited very long, any pause)
        return Place(now, due + after, "waited very long: any pause" if desperate
                     else "right after a frame")
    # in the pause after the next frame (its arrival wakes us sooner)
    return Place(next_end, 0.0, "after the next frame")


class Line:
    """One serial line's timing; ``on_frame(frame, at)`` is told of every frame."""

    def __init__(self, adapter: ProtocolAdapter, baud: int, stats: Counters,
                 on_frame: Callable[[Frame, float], None]) -> None:
        self.adapter = adapter
        self.baud = baud
        self.stats = stats
        self.on_frame = on_frame
        self.framer = adapter.new_framer()
        self.attempt: Attempt | None = None
        self.last_rx = 0.0
        self.last_tx_end = 0.0
        self.busy_end = 0.0  # the end of the last attempt counted as busy time
        self.dirty = False  # noise or half a frame came in: wait for quiet
        self.hold_until = 0.0  # a retry's own answer may still come until then
        self.heard = bytearray()  # what came in since the last request (for the trace)

    def reset(self, now: float) -> None:
        """The port (re)opened: nothing is known to be on the line."""
        self.framer = self.adapter.new_framer()
        self.attempt = None
        self.dirty = False
        self.last_rx = self.last_tx_end = now
        self.hold_until = 0.0

    @property
    def char(self) -> float:
        """One character's time on the wire."""
        return char_time(self.baud)

    @property
    def gap(self) -> float:
        return self.adapter.gap_before_request(self.baud)

    def wire(self, exchange: Exchange) -> float:
        """The exchange's request and answer at the line's rate, the gap between."""
        c = char_time(self.baud)
        return (len(exchange.request) + exchange.answer_bytes) * c + \
            (self.gap if exchange.answer_bytes else 0.0)

    @property
    def quiet(self) -> float:
        """How long the line must be silent after noise or half a frame."""
        return max(self.gap, 3.5 * self.char, MIN_QUIET)

    def free_at(self, now: float, pending: int = 0) -> float:
        """When the line is quiet enough for a request (the attempt in flight aside).
        ``pending``: bytes the port holds that ``receive`` has not had yet; while there
        are any, half a frame is not taken to have stopped (the rest is in the port: the
        loop is late, not the line quiet)."""
        quiet = self.quiet
        if self.framer.pending:
            if pending:
                return now + pending * self.char + MIN_QUIET
            return max(self.last_rx + quiet, self.last_tx_end + self.gap, self.hold_until)
        settle = quiet if self.dirty else self.gap
        return max(self.last_rx + settle, self.last_tx_end + self.gap, self.hold_until)

    def quiet_at(self, now: float) -> float:
        """When nothing more can come in answer to what was sent: the attempt in
        flight's hold (the bus's own wait for a late answer, with the grace for one
        arriving as it ends), else ``free_at``."""
        a = self.attempt
        return max(a.give_up + ARRIVING_GRACE if a is not None else now, self.free_at(now))

    def send(self, job: Job, exchange: Exchange, now: float, timeout: float,
             hold: float, place: Place, early: float = 0.0) -> Request:
        """``exchange`` goes out now (``free_at`` said the line is free); its answer is
        due ``timeout`` beyond the wire time, and the line is held ``hold`` more for a
        late one.  Half a frame still in the framer has stopped coming (the line has
        been quiet): it is dropped now, not while nothing needed the line (its rest may
        yet come, late, on a busy machine).  ``early``: the answer's latency is rarely
        less (0: not known, or to be timed); the port is not looked at before.
        ``place``: where it was placed next to a stream (with none, now, written by
        whenever)."""
        self.flush(now)
        wire = self.wire(exchange)
        if not exchange.answer_bytes:
            timeout = hold = 0.0
        deadline = now + wire + timeout
        self.attempt = Attempt(job, exchange, now, wire, deadline, deadline + hold,
                               now - self.gap, self.adapter.garbage_seen(self.framer),
                               tx_end_before=self.last_tx_end, looked=early > 0,
                               placed=place.why, clear_by=place.latest + place.room)
        self.last_tx_end = now + len(exchange.request) * char_time(self.baud)
        self.heard.clear()
        job.tries += 1
        look = wire + early if early > 0 else 0.0
        return Request(exchange.request, exchange.answer_bytes, place.latest, look)

    def written(self, at: float) -> None:
        """The request handed out was written by ``at`` (when the write returned).

        A write normally returns at once.  One that took longer (the thread was held
        off the CPU in it: a busy machine, a virtual machine's host) may have put the
        bytes on the line at any time until ``at``, so the answer is waited for as if
        they left then: its deadline and hold move on by the delay, and the line is
        not used before the request's own end.  The send time stays the earliest it
        could have been, since an answer is recognised by not coming before it, and
        the answer times nothing: from which moment would it be measured?

        Next to a stream, a write that returned too late for its exchange to end
        before the stream's next frame may have met that frame: counted
        (``late_writes``).  The place was checked just before the write; the thread
        was held between the two, in the write, or after it."""
        a = self.attempt
        if a is not None and at > a.clear_by:
            self.stats.late_writes += 1
        if a is None or at - a.sent <= SLOW_WRITE:
            return
        delay = at - a.sent
        a.deadline += delay
        a.give_up += delay
        a.untimed = True
        self.last_tx_end += delay

    def withdraw(self) -> None:
        """The request handed out was not written (it was too late for its place):
        as if it had never been sent."""
        a = self.attempt
        if a is not None:
            self.attempt = None
            self.last_tx_end = a.tx_end_before
            a.job.tries -= 1

    def receive(self, data: bytes, at: float) -> None:
        """Bytes from the line; ``at``: when the last of them came in."""
        self.last_rx = at
        if len(self.heard) < HEARD_MAX:
            self.heard += data[:HEARD_MAX - len(self.heard)]
        garbage = self.adapter.garbage_seen(self.framer)
        for frame in self.framer.feed(data):
            self.on_frame(frame, at)
        # Bytes that did not end in a whole frame (noise, half a frame) may be followed
        # by more: the next request then waits for the line to be quiet.
        self.dirty = bool(self.framer.pending) or \
            self.adapter.garbage_seen(self.framer) > garbage

    def check(self, now: float, pending: int) -> Due:
        """The attempt's deadlines at ``now``; ``pending``: bytes the port holds that
        ``receive`` has not had yet.  Bytes on their way (or half a frame still coming
        in) push a deadline back, but never past the hold plus ``ARRIVING_GRACE``: a
        line that chatters must not keep an attempt open for ever."""
        a = self.attempt
        if a is None:
            return Due.NOTHING
        if not a.exchange.answer_bytes:
            return Due.SENT if now >= a.deadline else Due.NOTHING
        limit = a.give_up + ARRIVING_GRACE
        if self.framer.pending and not pending and now >= self.last_rx + self.quiet:
            self.flush(now)  # a half frame that stopped coming: it never completes
            if self.attempt is not a:
                return Due.NOTHING  # what it held answered the attempt
        arriving = pending > 0 or bool(self.framer.pending)
        if not a.overdue:
            if now < a.deadline:
                return Due.NOTHING
            if arriving and self._wait_for_bytes(a, now, pending, limit):
                return Due.NOTHING
            a.overdue = True
        if now < a.give_up:
            return Due.NOTHING
        if arriving and self._wait_for_bytes(a, now, pending, limit):
            return Due.NOTHING
        return Due.FAILED

    def _wait_for_bytes(self, a: Attempt, now: float, pending: int, limit: float) -> bool:
        """Bytes are coming in at a deadline: wait for them rather than call the answer
        missing.  Up to ``limit`` while they arrive; past it only for bytes stuck in
        the port while nothing has reached ``receive`` since the limit (the reader
        thread is starved on a busy machine, not the line chattering), and never past
        ``STUCK_MAX``: a line that chatters must not keep the attempt open."""
        if now >= limit and not (pending and self.last_rx < limit and
                                 now < limit + STUCK_MAX):
            return False
        a.deadline = max(a.deadline, now + max(pending, 1) * self.char + MIN_QUIET)
        return True

    def failure_kind(self, a: Attempt) -> str:
        """``bad_frame`` when noise or a bad checksum came during the attempt."""
        return "bad_frame" if self.adapter.garbage_seen(self.framer) > a.garbage else "timeout"

    def close(self, a: Attempt, end: float, answered: bool) -> None:
        """The attempt is over at ``end``: its time on the line is counted (the silent
        gap before the request too, but not twice: it starts at the exchange before,
        counted up to its end)."""
        self.attempt = None
        took = max(0.0, end - max(a.started, self.busy_end))
        self.busy_end = max(self.busy_end, end)
        self.stats.busy_time += took
        a.job.sensor.stats.busy_time += took
        if answered:
            self.stats.transactions += 1
            a.job.sensor.stats.transactions += 1
            self.stats.rate.add(end)
            self.stats.wire_time += a.wire + self.gap

    def flush(self, now: float) -> None:
        """A half frame that stopped coming will never complete: whatever it held."""
        while self.framer.pending:
            for frame in self.framer.expire():
                self.on_frame(frame, now)
        self.dirty = False
