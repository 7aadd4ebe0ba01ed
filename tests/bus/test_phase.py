"""The phase of a stream, from frames seen late by varying amounts (``bus.phase``).

Each case feeds frames whose true ends are known (``1.0 + k * period``) through lags
of a stated shape, and checks where the estimator puts them.  No clock, no port."""

from __future__ import annotations

import random

import pytest

from imu_gateway.bus.phase import EARLY, WINDOW, StreamPhase

PERIOD = 0.01  # 100 Hz, as the busy-machine benchmark's MINS


def feed(phase: StreamPhase, lags: list[float], start: int = 0) -> list[float]:
    """Frames ``start``, ``start + 1``, … seen ``lags`` late; their arrival times."""
    seen = []
    for k, lag in enumerate(lags, start):
        at = 1.0 + k * PERIOD + lag
        phase.seen(at)
        seen.append(at)
    return seen


def small_lags(count: int, seed: int = 1) -> list[float]:
    """What a quiet machine shows: a fraction of a millisecond, now and then more."""
    rng = random.Random(seed)
    return [rng.expovariate(1 / 0.0003) for _ in range(count)]


def test_frames_seen_a_little_late_put_the_phase_at_their_front() -> None:
    phase = StreamPhase(PERIOD)
    seen = feed(phase, small_lags(100))
    assert phase.end_of(seen[-1]) == pytest.approx(1.0 + 99 * PERIOD, abs=0.0003)


def test_a_frame_seen_most_of_a_period_late_is_not_taken_for_the_next_one() -> None:
    """At 100 Hz a frame seen 9.5 ms late: it ended 9.5 ms ago, and the next is due in
    half a millisecond, not in a whole period."""
    phase = StreamPhase(PERIOD)
    feed(phase, small_lags(50))
    late = feed(phase, [0.0095], start=50)[0]
    assert phase.end_of(late) == pytest.approx(1.0 + 50 * PERIOD, abs=0.0003)
    assert phase.end_of(late) + PERIOD - late < 0.001  # the next frame is close


def test_a_run_of_late_frames_does_not_move_the_phase() -> None:
    """Three frames in a row seen 6-9 ms late, then quiet again."""
    phase = StreamPhase(PERIOD)
    feed(phase, small_lags(50))
    feed(phase, [0.006, 0.009, 0.0075], start=50)
    seen = feed(phase, small_lags(5, seed=2), start=53)
    assert phase.end_of(seen[-1]) == pytest.approx(1.0 + 57 * PERIOD, abs=0.0003)


def test_a_frame_a_sliver_early_is_that_frame_and_one_more_early_is_the_one_before() -> None:
    phase = StreamPhase(PERIOD)
    seen = feed(phase, [0.0] * 40)
    true_end = 1.0 + 40 * PERIOD
    assert phase.end_of(true_end - EARLY * PERIOD / 2) == pytest.approx(true_end)
    # Earlier than that it is taken for the frame before, seen late: that costs a
    # pause, never a collision.
    assert phase.end_of(true_end - 2 * EARLY * PERIOD) == pytest.approx(true_end - PERIOD)
    assert phase.end_of(seen[-1]) == pytest.approx(seen[-1])


def test_a_lasting_change_of_delay_moves_the_phase_within_a_window() -> None:
    """An adapter that now holds every frame 3 ms: after a window of frames the phase
    is the new front (nothing can tell a constant delay from a phase)."""
    phase = StreamPhase(PERIOD)
    feed(phase, small_lags(50))
    seen = feed(phase, [0.003 + lag for lag in small_lags(40, seed=3)], start=50)
    assert phase.end_of(seen[-1]) == pytest.approx(1.0 + 89 * PERIOD + 0.003, abs=0.0003)


@pytest.mark.parametrize("drift", [-0.0005, 0.0005])
def test_a_sensor_clock_a_little_off_is_followed(drift: float) -> None:
    """A sensor's clock 500 ppm fast or slow (a poor crystal): 200 s of frames."""
    phase = StreamPhase(PERIOD)
    rng = random.Random(4)
    at = 0.0
    for k in range(20_000):
        true_end = 1.0 + k * PERIOD * (1 + drift)
        at = true_end + rng.expovariate(1 / 0.0003)
        phase.seen(at)
    # Off by at most what the clock drifts across the window (0.32 ms here), well
    # inside the margin a request next to a stream keeps (a tenth of a period).
    assert abs(phase.end_of(at) - true_end) < WINDOW * PERIOD * abs(drift)


def test_nothing_seen_yet_means_no_phase() -> None:
    phase = StreamPhase(PERIOD)
    assert phase.anchor is None
    assert phase.end_of(5.0) == 5.0


def test_a_busy_spell_longer_than_a_cluster_does_not_move_the_phase() -> None:
    """Ten frames in a row seen 7 ms late (more than half a period: on the circle they
    sit 3 ms *before* the on-time frames) must not become the phase."""
    phase = StreamPhase(PERIOD)
    feed(phase, small_lags(60))
    late = feed(phase, [0.007 + lag / 10 for lag in small_lags(10, seed=5)], start=60)
    assert phase.end_of(late[-1]) == pytest.approx(1.0 + 69 * PERIOD, abs=0.0003)
