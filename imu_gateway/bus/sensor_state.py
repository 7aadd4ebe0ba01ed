"""One sensor's state on its bus, and the rules that change it: back-off, online and
offline, the poll timetable, and the evidence that it streams unasked.  Sans-IO: every
method takes the time as an argument.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

from ..config import SensorConfig
from ..protocol.exchanges import Exchange, ProtocolAdapter
from ..stats import Counters
from .phase import StreamPhase
from .timing import WIDE_EVERY, AnswerTimer, probe_timeout

OFFLINE_AFTER = 3  # consecutive failed exchanges before a sensor is called offline
BACKOFF_MIN, BACKOFF_MAX = 0.25, 10.0  # seconds between tries of a failing sensor
#: The share of a line's time all its dead sensors' probes may take together, while a
#: sensor on it answers: a probe of a sensor that is not answering (never yet, or offline)
#: that held the line T seconds is followed by the next one no sooner than
#: T * dead / PROBE_BUDGET seconds later (and no sooner than its back-off).
PROBE_BUDGET = 0.02
STREAM_RETRY = 5.0  # seconds before setting up (or stopping) a stream again
#: seconds before a failed settings read of a sensor back from offline is tried again
SETTINGS_RETRY = 5.0
# A sensor is taken to stream unasked only on evidence a late answer cannot give:
# EVIDENCE_FRAMES frames nobody asked for within EVIDENCE_WINDOW seconds, spread over
# at least EVIDENCE_SPAN seconds, each arriving with no request to that sensor
# outstanding and none of its unanswered requests left to explain it.
EVIDENCE_FRAMES, EVIDENCE_SPAN, EVIDENCE_WINDOW = 5, 2.0, 5.0
#: An unanswered request may still be answered (very late) this long after it was sent:
#: a frame from its sensor within that time is taken for that answer, not for a stream.
LATE_MEMORY = 10.0
#: A request sent this soon after one that went unanswered may get that one's answer:
#: its own answer is then not trusted to time anything, and is waited for.
SUSPECT = 1.0


@dataclass(eq=False, slots=True)
class SensorState:
    """A sensor's run-time state on its bus."""

    config: SensorConfig
    address: int
    timer: AnswerTimer = field(default_factory=AnswerTimer)
    stats: Counters = field(default_factory=Counters)
    next_due: float = 0.0
    last_served: float = 0.0
    failures: int = 0
    online: bool | None = None  # None: not heard from yet
    busy_until: float = 0.0
    read_while_busy: bool = False
    streaming: bool = False
    last_stream: float = 0.0  # when its last stream frame's last byte came in
    stream_frames: int = 0  # frames since the stream was set up (0: its phase is unknown)
    phase: StreamPhase | None = None  # when its stream's frames really end
    stream_retry_at: float = 0.0
    stop_stream: bool = False  # it streams though nobody asked: tell it to stop
    evidence: deque[float] = field(default_factory=deque)  # unexplained frames' times
    unanswered: deque[float] = field(default_factory=lambda: deque(maxlen=64))
    #: when its settings are to be read (``read_settings``, by the bus itself): after it
    #: was offline, what a command set may have been undone by a power cut (inf: never)
    settings_at: float = math.inf
    #: every sensor on its line, itself too (one list, shared): how many are dead
    line: list[SensorState] = field(default_factory=list, repr=False)
    probes: int = 0  # probe attempts sent (one in ``WIDE_EVERY`` waits longer)
    #: removed by a reload: no new job; it leaves once nothing of it is in flight
    leaving: bool = False
    _busy_mark: float = 0.0  # its line time when its last poll ended
    _probing: bool = True  # its next poll is a probe (it was not answering when it was set)
    _poll: tuple[int, Exchange] | None = None

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def period(self) -> float:
        return 1 / self.config.poll_hz if self.config.poll_hz > 0 else 0.0

    @property
    def stream_timeout(self) -> float:
        """Frames missing this long mean the stream has stopped."""
        return max(5 / self.config.stream_hz, 0.5) if self.config.stream_hz else 0.0

    def poll(self, adapter: ProtocolAdapter) -> Exchange:
        """Its poll, built once per address (it is sent hundreds of times a second, and
        the time between an answer and the next request is the line's)."""
        if self._poll is None or self._poll[0] != self.address:
            self._poll = (self.address, adapter.poll(self.config.series, self.address))
        return self._poll[1]

    def wants_stream(self, now: float) -> bool:
        return bool(self.config.stream_hz) and not self.streaming \
            and now >= self.stream_retry_at and now >= self.busy_until

    def settings_due(self, now: float) -> bool:
        """Are its settings to be read now?  Only while it answers and is not busy, at
        the turn of its poll (a streaming sensor: at once)."""
        return self.settings_at <= now and self.online is True and \
            self.busy_until <= now and (self.streaming or self.next_due <= now)

    def due(self, now: float) -> bool:
        return self.next_due <= now and (self.busy_until <= now or self.read_while_busy) \
            and not self.streaming

    # ------------------------------------------------------------ answers and failures

    def succeeded(self) -> str | None:
        """It answered: "online" or "recovered" when that changes what it is, else None."""
        self.failures = 0
        if self.online is True:
            return None
        change = "recovered" if self.online is False else "online"
        if self.online is False:  # (it may have lost power meanwhile)
            self.settings_at = 0.0
        self.online = True
        return change

    def failed(self) -> bool:
        """An exchange failed (all its attempts).  True when this makes it offline."""
        self.failures += 1
        if self.failures == OFFLINE_AFTER and self.online is not False:
            self.online = False
            return True
        return False

    @property
    def dead(self) -> bool:
        """Not answering: never yet, or offline (its polls are probes)."""
        return self.online is not True and self.failures > 0

    def schedule_next_poll(self, now: float) -> None:
        """After a poll: the next one at its rate, or after a back-off when failing.
        Polls that fell more than a period behind are counted as missed, not fired
        later as a burst of catch-up reads."""
        held, self._busy_mark = self.stats.busy_time - self._busy_mark, self.stats.busy_time
        if self.failures:
            # (the exponent is capped: a sensor away for days fails without end, and
            # 2 ** 1024 is past a float)
            wait = min(BACKOFF_MAX, BACKOFF_MIN * 2 ** min(self.failures - 1, 32))
            # Only a probe is charged to the budget: the poll that found it gone waited
            # its own learned timeouts, and charging those spaced the first probe 45 s
            # away (a stalled sensor of the soak was found again after 46 s).
            if self._probing and self.dead and any(t.online for t in self.line):
                # its share of the probe budget of a line others use (one not answering
                # yet counts as dead: at startup too, no probe takes more than its share)
                dead = sum(t.online is not True for t in self.line)
                wait = max(wait, held * dead / PROBE_BUDGET)
            self.next_due = now + wait
            self._probing = self.dead
            return
        self._probing = False
        if self.period == 0:
            self.next_due = now
        else:
            self.next_due += self.period
            if self.next_due < now - self.period:
                missed = int((now - self.next_due) / self.period)
                self.stats.missed_polls += missed
                self.next_due += missed * self.period
            self.next_due = max(self.next_due, now - self.period)

    # ------------------------------------------------------------ its stream

    def stream_started(self, at: float) -> None:
        """It streams from ``at`` on; the phase is unknown until its first frame."""
        self.streaming, self.last_stream, self.stream_frames = True, at, 0

    def stream_ended(self) -> None:
        self.streaming, self.stream_frames = False, 0

    # ------------------------------------------------------------ its stream's phase

    def stream_frame(self, at: float) -> None:
        """A frame of its stream ended at ``at`` (as far as this machine can tell)."""
        if not self.stream_frames and self.config.stream_hz:
            self.phase = StreamPhase(1 / self.config.stream_hz)  # a new stream: a new phase
        if self.phase is not None:
            self.phase.seen(at)
        self.last_stream = at
        self.stream_frames += 1

    def frame_end_before(self, at: float) -> float:
        """The true end, in phase, of the frame last seen at ``at`` or before."""
        if not self.stream_frames or self.phase is None:
            return self.last_stream
        return self.phase.end_of(self.last_stream)

    # ------------------------------------------------------------ stream evidence

    def suspect(self, sent: float) -> bool:
        """Did a request to it go unanswered shortly before ``sent``?  Then an answer to
        the request sent at ``sent`` may be that one's, late."""
        return bool(self.unanswered) and sent - self.unanswered[-1] < SUSPECT

    def explained(self, at: float) -> bool:
        """Is a frame of this sensor at ``at`` the late answer to an unanswered request?
        If so that request is answered now (one frame per request)."""
        while self.unanswered and at - self.unanswered[0] > LATE_MEMORY:
            self.unanswered.popleft()
        if self.unanswered:
            self.unanswered.popleft()
            return True
        return False

    def unasked_frame(self, at: float) -> bool:
        """A frame nobody asked for, that no request explains.  True when the frames
        are now evidence enough that it streams (steady over seconds)."""
        self.evidence.append(at)
        while self.evidence and at - self.evidence[0] > EVIDENCE_WINDOW:
            self.evidence.popleft()
        if len(self.evidence) >= EVIDENCE_FRAMES and \
                self.evidence[-1] - self.evidence[0] >= EVIDENCE_SPAN:
            self.evidence.clear()
            return True
        return False


def probe_times(s: SensorState, sensors: Iterable[SensorState]) -> tuple[float, float]:
    """The timeout and hold of a probe of a sensor not answering (never yet, or
    offline): from its live neighbours' latency, without back-off, for it must cost
    them little; one attempt in ``WIDE_EVERY`` waits longer (``timing``)."""
    if s.timer.fixed is not None:
        return s.timer.fixed, s.timer.fixed  # (the config's own word)
    s.probes += 1
    live = [t.timer for t in sensors if t.online]
    hold = probe_timeout(live, s.timer)
    wide = s.probes % WIDE_EVERY == 1
    return (probe_timeout(live, s.timer, wide=True) if wide else hold), hold
