"""How long to wait for a sensor's answer, learned from its answers.

A sensor's answer comes after its own turnaround (its MCU: 1-40 ms), plus whatever a
USB adapter holds the bytes for (an FTDI latency timer: 16 ms by default), plus how
late this machine gets round to them.  None of that is known in advance, and it is
not the same for every sensor on a line.  So each sensor's answer latency is measured
and its timeout derived the way TCP derives its retransmission timeout (RFC 6298):
a smoothed latency plus four mean deviations, with a floor and a cap.  After a
timeout the next attempt waits twice as long (RFC 6298 §5.5), until an answer
brings a new measurement.  Past its timeout an answer is still listened for, for
another timeout (``hold``): one that comes then is late, but used and measured.

The latency is the time from the request's last byte to the answer's last byte,
less the answer's own wire time: what the sensor and the adapter added.

A sensor that has not answered yet, or has gone offline, has no latency of its own
worth trusting, and waiting for it costs the sensors that do answer.  It is probed with
a timeout from what the line knows (``probe_timeout``): the slowest latency its live
neighbours are expected to reach, times ``PROBE_MARGIN``, never less than ``RTO_MIN`` nor
more than ``PROBE_MAX``, and never doubled.  The adapter's latency is the line's, so the
neighbours measure it.  A sensor that answered before is waited for at least as long as
its own latency asks; one never heard, and far slower than its neighbours, is still
found by the one probe attempt in ``WIDE_EVERY`` that waits the first-answer timeout.

The estimate also says when to *look* for an answer: an answer that cannot be whole
before its usual latency needs no wake-up for its first bytes (each wake-up costs CPU;
at a few hundred exchanges a second, most of the gateway's).  An answer found whole at
such a look came in at some unknown time before it, so it times nothing; one answer in
``LOOK_EVERY`` is watched for from the request on, and keeps the estimate learning.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

#: Before a sensor has answered: a 40 ms turnaround behind a 16 ms adapter, with room.
RTO_INITIAL = 0.1
#: Never less: a sensor measured at 2 ms with no spread still gets this much.
RTO_MIN = 0.01
#: Never more: past this a sensor is not answering, and waiting costs the others.
RTO_MAX = 0.4
_ALPHA, _BETA, _K = 1 / 8, 1 / 4, 4  # RFC 6298's gains and deviation factor
#: A probe (of a sensor not answering) waits its neighbours' latency times this.
PROBE_MARGIN = 2.0
#: A probe never waits longer than this: a dead sensor must cost the others little.
PROBE_MAX = 0.1
#: One probe attempt in this many waits the first-answer timeout (a slow sensor among
#: fast neighbours is found by it).
WIDE_EVERY = 8
#: One answer in this many is watched for from its request on (and times the sensor).
LOOK_EVERY = 8


@dataclass(slots=True)
class AnswerTimer:
    """One sensor's answer latency estimate and its timeout, in seconds.

    ``fixed`` (the config's ``timeout_ms``) overrides the learned timeout; the
    latency is still measured and shown."""

    fixed: float | None = None
    srtt: float | None = None  # smoothed latency; None until the first answer
    rttvar: float = 0.0  # its mean deviation
    backoff: int = 0  # timeouts since the last answer: each doubles the timeout
    samples: int = 0
    looks: int = 0  # requests given a look time (``look_after``)

    def sample(self, latency: float) -> None:
        """An answer came ``latency`` seconds after its request left (never negative)."""
        latency = max(0.0, latency)
        if self.srtt is None:
            self.srtt, self.rttvar = latency, latency / 2
        else:
            self.rttvar = (1 - _BETA) * self.rttvar + _BETA * abs(self.srtt - latency)
            self.srtt = (1 - _ALPHA) * self.srtt + _ALPHA * latency
        self.backoff = 0
        self.samples += 1

    def answered(self) -> None:
        """An answer came that times nothing (found whole at a look): it still ends
        the back-off."""
        self.backoff = 0

    def look_after(self) -> float:
        """How long past a request's wire time its answer cannot be whole yet, as far
        as the sensor's answers tell: the bus need not look before then.  0: watch for
        it from the request on (no estimate yet, or the one in ``LOOK_EVERY`` that
        times the sensor)."""
        self.looks += 1
        if self.srtt is None or self.backoff or self.looks % LOOK_EVERY == 0:
            return 0.0
        return max(0.0, min(self.srtt - 2 * self.rttvar, self.rto))

    def timed_out(self) -> None:
        """An attempt got no answer: the next one waits longer, up to the cap."""
        if self.rto < RTO_MAX:
            self.backoff += 1

    @property
    def learned(self) -> float:
        """The timeout the measurements alone give (no back-off)."""
        if self.srtt is None:
            return RTO_INITIAL
        return min(RTO_MAX, max(RTO_MIN, self.srtt + _K * self.rttvar))

    @property
    def rto(self) -> float:
        """How long to wait beyond the wire time for the next answer."""
        if self.fixed is not None:
            return self.fixed
        return min(RTO_MAX, self.learned * (1 << self.backoff))

    @property
    def hold(self) -> float:
        """How long the line stays held for a late answer after an attempt's timeout:
        one timeout as learned, without the back-off (a dead address must cost the
        others little)."""
        return self.fixed if self.fixed is not None else self.learned

    def expected(self) -> float:
        """A latency the sensor will rarely exceed (to fit an exchange into a pause)."""
        if self.srtt is None:
            return 0.0  # unknown: assume a fast sensor, and learn
        return self.srtt + _K * self.rttvar


def probe_timeout(neighbours: Iterable[AnswerTimer], own: AnswerTimer,
                  wide: bool = False) -> float:
    """The timeout (and hold) of a probe of a sensor that is not answering, from its
    live ``neighbours``' timers: the latency the slowest of them is expected to reach,
    times ``PROBE_MARGIN``, within ``RTO_MIN`` and ``PROBE_MAX``.  A sensor that answered
    before (``own``) is waited for at least as long as it used to need.  With no
    neighbour that has answered, or ``wide``: the first-answer timeout, capped."""
    expected = [t.expected() for t in neighbours if t.srtt is not None]
    if wide or not expected:
        return min(RTO_INITIAL, PROBE_MAX)
    return min(PROBE_MAX, max(RTO_MIN, max([*expected, own.expected()]) * PROBE_MARGIN))
