"""Consistency of the simulated motion: every group derives from the same attitude."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from imu_gateway.model import Quaternion, Reading, Vector3
from imu_gateway.simulator.motion import Fixed, Leaned, Motion, Source, hold

Q = tuple[float, float, float, float]
times = st.floats(min_value=0.0, max_value=600.0)
seeds = st.integers(min_value=0, max_value=10_000)


def mul(a: Q, b: Q) -> Q:
    return (
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


def tup(q: Quaternion | None) -> Q:
    assert q is not None
    return (q.q0, q.q1, q.q2, q.q3)


def vec(v: Vector3 | None) -> tuple[float, float, float]:
    assert v is not None
    return (v.x, v.y, v.z)


def to_body(q: Q, v: tuple[float, float, float]) -> tuple[float, float, float]:
    """q rotates body to NED, so a NED vector in body axes is q* ⊗ v ⊗ q."""
    conj = (q[0], -q[1], -q[2], -q[3])
    r = mul(mul(conj, (0.0, *v)), q)
    return (r[1], r[2], r[3])


def close(a: tuple[float, ...], b: tuple[float, ...], tol: float) -> bool:
    return all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


def same_rotation(a: Q, b: Q, tol: float) -> bool:
    return close(a, b, tol) or close(a, tuple(-c for c in b), tol)


@given(seeds, times)
def test_gyro_is_the_derivative_of_the_attitude(seed: int, t: float) -> None:
    # Integrate q' = ½ q ⊗ (0, ω) over dt with the midpoint rate: the error is O(dt³), far
    # below what a wrong sign or a missing term in the rate equations would cause (~dt·ω).
    m, dt = Motion.from_seed(seed), 1e-3
    w = tuple(math.radians(c) for c in vec(m.sample(t + dt / 2).gyro))
    norm = math.sqrt(sum(c * c for c in w))
    half = norm * dt / 2
    k = math.sin(half) / norm if norm else 0.0
    step = (math.cos(half), w[0] * k, w[1] * k, w[2] * k)
    integrated = mul(tup(m.sample(t).quaternion), step)
    assert same_rotation(integrated, tup(m.sample(t + dt).quaternion), 1e-9)


@given(seeds, times)
def test_quaternion_matches_the_euler_angles(seed: int, t: float) -> None:
    r = Motion.from_seed(seed).sample(t)
    q0, q1, q2, q3 = tup(r.quaternion)
    assert q0 >= 0 and math.isclose(q0**2 + q1**2 + q2**2 + q3**2, 1.0, abs_tol=1e-12)
    roll = math.degrees(math.atan2(2 * (q0 * q1 + q2 * q3), 1 - 2 * (q1 * q1 + q2 * q2)))
    pitch = math.degrees(math.asin(2 * (q0 * q2 - q3 * q1)))
    yaw = math.degrees(math.atan2(2 * (q0 * q3 + q1 * q2), 1 - 2 * (q2 * q2 + q3 * q3)))
    assert r.angles is not None
    assert r.angles.roll == pytest.approx(roll, abs=1e-9)
    assert r.angles.pitch == pytest.approx(pitch, abs=1e-9)
    dyaw = (r.angles.yaw - yaw + 180.0) % 360.0 - 180.0  # atan2 gives (-180, 180]
    assert abs(dyaw) < 1e-9


@given(seeds, times)
def test_accel_and_mag_have_constant_magnitude(seed: int, t: float) -> None:
    m = Motion.from_seed(seed)
    r = m.sample(t)
    assert math.hypot(*vec(r.accel)) == pytest.approx(1.0, abs=1e-12)
    assert math.hypot(*vec(r.mag)) == pytest.approx(math.hypot(m.mag_north, m.mag_down))


@given(seeds, times)
def test_accel_and_mag_are_the_world_vectors_rotated_by_the_quaternion(seed: int, t: float) -> None:
    m = Motion.from_seed(seed)
    r = m.sample(t)
    q = tup(r.quaternion)
    assert close(vec(r.accel), to_body(q, (0.0, 0.0, 1.0)), 1e-12)
    assert close(vec(r.mag), to_body(q, (m.mag_north, 0.0, m.mag_down)), 1e-12)


def test_level_and_still() -> None:
    m = Motion(roll_amp=0.0, pitch_amp=0.0, yaw_rate=0.0)
    for t in (0.0, 1.5, 100.0):
        r = m.sample(t)
        assert close(vec(r.accel), (0.0, 0.0, 1.0), 1e-15)
        assert close(vec(r.gyro), (0.0, 0.0, 0.0), 1e-15)
        assert close(vec(r.mag), (0.2, 0.0, 0.42), 1e-15)  # north ahead, field dipping down
        assert close(tup(r.quaternion), (1.0, 0.0, 0.0, 0.0), 1e-15)


def test_heading_east_sees_north_on_the_left() -> None:
    r = Motion(roll_amp=0.0, pitch_amp=0.0, yaw0=90.0, yaw_rate=0.0).sample(0.0)
    assert close(vec(r.mag), (0.0, -0.2, 0.42), 1e-12)  # body y is right, so north is -y


def test_nose_up_and_right_wing_down_signs() -> None:
    # Positive pitch raises the nose: gravity shifts towards -x; positive roll: towards +y.
    r = Motion(
        roll_amp=10.0, pitch_amp=10.0, roll_phase=math.pi / 2, pitch_phase=math.pi / 2, yaw_rate=0.0
    ).sample(0.0)
    ax, ay, _ = vec(r.accel)
    assert ax < 0 < ay


def test_yaw_wraps_into_0_360() -> None:
    for m in (Motion(yaw0=350.0, yaw_rate=6.0), Motion(yaw0=10.0, yaw_rate=-6.0)):
        yaws = [r.angles.yaw for r in map(m.sample, range(200)) if r.angles]
        assert all(0.0 <= y < 360.0 for y in yaws)
    forward = Motion(yaw0=350.0, yaw_rate=6.0).sample(5.0).angles
    assert forward is not None and forward.yaw == pytest.approx(20.0)
    tiny = Motion(yaw0=0.0, yaw_rate=-1e-30).sample(1.0).angles  # -1e-30 % 360 == 360.0
    assert tiny is not None and tiny.yaw == 0.0


def test_from_seed_is_deterministic_and_varied() -> None:
    assert Motion.from_seed(7) == Motion.from_seed(7)
    assert Motion.from_seed(7).sample(12.5) == Motion.from_seed(7).sample(12.5)
    assert len({Motion.from_seed(s) for s in range(20)}) == 20


def test_ranges_fit_the_native_bcd_formats() -> None:
    for seed in range(51):
        m = Motion.from_seed(seed)
        for i in range(0, 6001, 7):  # t from 0 to 600 s in 0.7 s steps
            r = m.sample(i / 10)
            assert r.angles is not None
            assert all(abs(a) <= 999.99 for a in (r.angles.pitch, r.angles.roll, r.angles.yaw))
            assert all(abs(c) <= 9.9999 for c in vec(r.accel))
            assert all(abs(c) <= 999.99 for c in vec(r.gyro))
            assert all(abs(c) <= 0.99999 for c in vec(r.mag))
            assert all(abs(c) <= 9.999999 for c in tup(r.quaternion))


def test_hold_returns_the_fixed_reading() -> None:
    reading = Reading(accel=Vector3(0.01, -0.02, 1.0))
    source: Source = hold(reading)
    assert isinstance(source, Fixed)
    assert source.sample(0.0) is reading and source.sample(99.0) is reading


# ---------------------------------------------------------------- a lean (Leaned)

pitches = st.floats(min_value=-89.0, max_value=89.0)
rolls = st.floats(min_value=-180.0, max_value=180.0)


@given(seeds, times, pitches, rolls)
def test_a_lean_holds_pitch_and_roll_and_the_motion_s_heading(seed: int, t: float,
                                                              pitch: float, roll: float) -> None:
    m = Motion.from_seed(seed)
    r = Leaned(m, pitch, roll).sample(t)
    assert r.angles is not None and (r.angles.pitch, r.angles.roll) == (pitch, roll)
    assert r.angles.yaw == m.yaw(t) == m.sample(t).angles.yaw  # type: ignore[union-attr]


@given(seeds, times, pitches, rolls)
def test_a_lean_s_quaternion_accel_and_mag_match_its_angles(seed: int, t: float, pitch: float,
                                                            roll: float) -> None:
    m = Motion.from_seed(seed)
    r = Leaned(m, pitch, roll).sample(t)
    q = tup(r.quaternion)
    q0, q1, q2, q3 = q
    assert q0 >= 0 and math.isclose(q0**2 + q1**2 + q2**2 + q3**2, 1.0, abs_tol=1e-12)
    assert math.degrees(math.asin(2 * (q0 * q2 - q3 * q1))) == pytest.approx(pitch, abs=1e-9)
    qroll = math.degrees(math.atan2(2 * (q0 * q1 + q2 * q3), 1 - 2 * (q1 * q1 + q2 * q2)))
    assert abs((qroll - roll + 180.0) % 360.0 - 180.0) < 1e-9  # ±180° are one roll
    assert close(vec(r.accel), to_body(q, (0.0, 0.0, 1.0)), 1e-12)
    assert close(vec(r.mag), to_body(q, (m.mag_north, 0.0, m.mag_down)), 1e-12)


@given(seeds, times, pitches, rolls)
def test_a_lean_s_gyro_is_the_turn_of_its_heading(seed: int, t: float, pitch: float,
                                                  roll: float) -> None:
    """Held at the lean, the sensor still turns with the motion's yaw: integrating the
    gyro over dt gives the next sample's quaternion (as for the motion itself)."""
    lean, dt = Leaned(Motion.from_seed(seed), pitch, roll), 1e-3
    w = tuple(math.radians(c) for c in vec(lean.sample(t + dt / 2).gyro))
    norm = math.sqrt(sum(c * c for c in w))
    half = norm * dt / 2
    k = math.sin(half) / norm if norm else 0.0
    step = (math.cos(half), w[0] * k, w[1] * k, w[2] * k)
    integrated = mul(tup(lean.sample(t).quaternion), step)
    assert same_rotation(integrated, tup(lean.sample(t + dt).quaternion), 1e-9)


def test_a_lean_on_a_still_source_keeps_its_heading_and_stands_still() -> None:
    still = hold(Motion(yaw0=123.0, yaw_rate=0.0, roll_amp=0.0, pitch_amp=0.0).sample(0.0))
    r = Leaned(still, 0.0, 0.0).sample(5.0)
    assert r.angles is not None and r.angles.yaw == 123.0
    assert close(vec(r.gyro), (0.0, 0.0, 0.0), 1e-15)
    assert close(vec(r.accel), (0.0, 0.0, 1.0), 1e-15)
    nose_up = Leaned(still, 10.0, 0.0).sample(0.0)  # gravity shifts towards -x
    assert vec(nose_up.accel)[0] == pytest.approx(-math.sin(math.radians(10.0)))


@pytest.mark.parametrize(("pitch", "roll"), [(math.nan, 0.0), (0.0, math.inf), (89.5, 0.0),
                                             (-90.0, 0.0), (0.0, 180.5), (0.0, -200.0)])
def test_a_lean_out_of_range_is_refused(pitch: float, roll: float) -> None:
    with pytest.raises(ValueError, match=r"a lean's (pitch|roll) is a number of degrees"):
        Leaned(Motion(), pitch, roll)
