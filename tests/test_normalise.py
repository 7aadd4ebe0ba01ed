"""Decoded values to the normalised ``Reading`` (``imu_gateway.normalise``).

A reading carries exactly the groups the series measures (``model.CAPABILITIES``),
whichever protocol the values came from; partial groups are left out; the AH
example of the native document gives exactly the value groups of the example reading JSON
in docs/mqtt.md.
"""

from __future__ import annotations

import math
import random
from datetime import UTC, datetime, timedelta, timezone
from zoneinfo import ZoneInfo

import pytest
from support.vectors import ANSWER, NATIVE_VECTORS, Vector

from imu_gateway.cache import Cache, EventKind, Snapshot, iso_time
from imu_gateway.model import (
    CAPABILITIES,
    MEASURED_GROUPS,
    VALUE_GROUPS,
    Angles,
    Group,
    Quaternion,
    Reading,
    Series,
    Tilt,
    Vector3,
    Vibration,
)
from imu_gateway.normalise import (
    FIELD_NAMES,
    Derivation,
    VibrationWindow,
    group_values,
    tilt_of,
    to_reading,
)
from imu_gateway.protocol import modbus_rtu as rtu
from imu_gateway.protocol import native
from imu_gateway.simulator.motion import Motion

# The reading JSON's value groups of the AH example of native 2.15 (as in docs/mqtt.md).
SPEC_JSON_GROUPS = {
    "angles": {"pitch": -13.15, "roll": 25.58, "yaw": 251.87},
    "accel": {"x": -0.1807, "y": -0.2816, "z": 1.0265},
    "gyro": {"x": -6.48, "y": 124.13, "z": 3.88},
    "mag": {"x": 0.15962, "y": 0.16391, "z": -0.41458},
    "quaternion": {"q0": -0.228375, "q1": -0.183349, "q2": -0.165578, "q3": 0.939914},
}


def answer(section: str) -> Vector:
    return next(v for v in NATIVE_VECTORS if v.section == section and v.direction == ANSWER)


def decoded(section: str) -> dict[str, object]:
    v = answer(section)
    return dict(native.decode(v.raw, v.series).values)


@pytest.mark.parametrize(
    ("section", "series"),
    [("2.13", Series.IMU), ("2.14", Series.VG), ("2.14", Series.MINS), ("2.15", Series.AH)],
)
def test_native_read_all_gives_the_series_groups(section: str, series: Series) -> None:
    reading = to_reading(decoded(section), series)
    assert reading is not None
    assert reading.groups() == CAPABILITIES[series].measured


def test_native_imu_reading_values() -> None:
    reading = to_reading(decoded("2.13"), Series.IMU)
    assert reading == Reading(
        accel=Vector3(0.0107, 0.9421, -0.0630), gyro=Vector3(-93.76, -298.87, 14.03)
    )


def test_ah_example_gives_spec_json_groups() -> None:
    reading = to_reading(decoded("2.15"), Series.AH)
    assert reading is not None
    assert reading.to_json_groups() == SPEC_JSON_GROUPS
    assert list(reading.to_json_groups()) == list(SPEC_JSON_GROUPS)  # the same order


def test_modbus_float_block_for_vg_drops_mag() -> None:
    values = dict(decoded("2.15"))  # an AH-like set of sixteen values, mag included
    image = rtu.register_image(values)
    start, count = rtu.FLOAT_BLOCK_START, rtu.FLOAT_BLOCK_COUNT
    assert (start, count) == (0x22, 32)
    read = rtu.read_values(start, [image[a] for a in range(start, start + count)])
    assert set(read) == {n for g in MEASURED_GROUPS for n in VALUE_GROUPS[g].fields}
    vg = to_reading(read, Series.VG)
    assert vg is not None
    assert vg.mag is None
    assert vg.groups() == CAPABILITIES[Series.VG].measured
    assert vg.angles == Angles(-13.15, 25.58, 251.87)
    ah = to_reading(read, Series.AH)
    assert ah is not None and ah.mag == Vector3(0.15962, 0.16391, -0.41458)


def test_modbus_zero_mag_registers_of_vg_are_not_measured() -> None:
    values = {name: 0.0 for name in FIELD_NAMES} | {"pitch": 1.0, "q0": 1.0}
    image = rtu.register_image(values)
    start = rtu.FLOAT_BLOCK_START
    read = rtu.read_values(start, [image[a] for a in range(start, start + 32)])
    reading = to_reading(read, Series.VG)
    assert reading is not None and Group.MAG not in reading.groups()


def test_partial_group_is_left_out() -> None:
    """A 2.1 answer carries the pitch alone: no whole angle group, so no reading.  The
    cache never mixes it with an older roll and yaw under a new timestamp."""
    assert decoded("2.1") == {"pitch": -34.63}
    assert to_reading(decoded("2.1"), Series.VG) is None
    assert to_reading({**decoded("2.1"), **decoded("2.10")}, Series.VG) == Reading(
        accel=Vector3(0.0107, 0.9421, -0.063)
    )


def test_whole_group_gives_a_reading() -> None:
    assert to_reading(decoded("2.3"), Series.MINS) == Reading(angles=Angles(2.01, -0.51, 0.0))
    assert to_reading(decoded("2.12"), Series.VG) == Reading(
        quaternion=Quaternion(0.999996, 0.000290, -0.002673, -0.000001)
    )


def test_group_outside_the_series_gives_no_reading() -> None:
    assert to_reading(decoded("2.23"), Series.VG) is None  # a mag answer, VG has no mag
    assert to_reading(decoded("2.3"), Series.IMU) is None


def test_non_measured_values_give_no_reading() -> None:
    assert to_reading({"result": "success"}, Series.AH) is None
    assert to_reading({}, Series.AH) is None


def test_group_values_partial() -> None:
    assert group_values(decoded("2.1")) == {"angles": {"pitch": -34.63}}
    assert group_values({"roll": 1.5, "accel_z": 1.0, "q3": 0.5, "result": "success"}) == {
        "angles": {"roll": 1.5},
        "accel": {"z": 1.0},
        "quaternion": {"q3": 0.5},
    }
    assert group_values({"zero_type": "relative"}) == {}


def test_group_values_whole() -> None:
    assert group_values(decoded("2.15")) == SPEC_JSON_GROUPS
    assert group_values(decoded("2.23")) == {"mag": {"x": -0.15525, "y": 0.03452, "z": -0.34616}}


# ------------------------------------------------------------------ derived values


@pytest.mark.parametrize(("pitch", "roll", "tilt", "direction"), [
    (10.0, 0.0, 10.0, 180.0),  # x raised: the top leans back (-x)
    (-10.0, 0.0, 10.0, 0.0),  # x lowered: forward
    (0.0, 10.0, 10.0, 90.0),  # right side down: leans right (+y)
    (0.0, -10.0, 10.0, 270.0),
    (179.0, 0.0, 179.0, 180.0),  # nearly upside down
    (90.0, 33.0, 90.0, 180.0),  # gimbal lock: the roll changes nothing
])
def test_tilt_and_its_direction_on_the_axes(pitch: float, roll: float, tilt: float,
                                            direction: float) -> None:
    assert tilt_of(Angles(pitch, roll, 123.0)) == Tilt(tilt, direction)


def test_tilt_agrees_with_the_gravity_the_simulator_gives() -> None:
    """The simulator's accelerations are gravity in the sensor's frame (x forward, y
    right, z down), made from the same pitch and roll by its own rotation: the tilt is
    z's angle from gravity, the direction gravity's heading in the x-y plane."""
    rng = random.Random(31)
    for _ in range(500):
        pitch, roll = rng.uniform(-89.0, 89.0), rng.uniform(-179.0, 179.0)
        # (at t = 0 with a phase of 90°, the sway is at its amplitude)
        still = Motion(roll_amp=roll, pitch_amp=pitch, roll_phase=math.pi / 2,
                       pitch_phase=math.pi / 2, yaw_rate=0.0).sample(0.0)
        assert still.angles is not None and still.accel is not None
        assert still.angles.pitch == pytest.approx(pitch)
        assert still.angles.roll == pytest.approx(roll)
        accel = still.accel
        got = tilt_of(Angles(pitch, roll, 0.0))
        assert got.tilt == pytest.approx(math.degrees(math.acos(accel.z)), abs=0.005)
        if got.tilt > 0.01:
            want = math.degrees(math.atan2(accel.y, accel.x)) % 360.0
            gap = abs(got.tilt_direction - want)
            assert min(gap, 360.0 - gap) <= 0.005 + 1e-9, (pitch, roll, got, want)


def test_tilt_is_rounded_and_has_no_direction_when_level() -> None:
    level = tilt_of(Angles(0.0, 0.0, 45.0))
    assert level.tilt == 0.0 and math.isnan(level.tilt_direction)
    almost = tilt_of(Angles(0.001, 0.002, 0.0))  # 0.0022°: 0.00 at two digits
    assert almost.tilt == 0.0 and math.isnan(almost.tilt_direction)
    # a direction of 359.999° is 0.00 at two digits, not 360.00
    assert tilt_of(Angles(-1.0, -0.00002, 0.0)).tilt_direction == 0.0
    assert tilt_of(Angles(3.0, 4.0, 0.0)) == Tilt(5.0, 126.92)
    nan = tilt_of(Angles(math.nan, 1.0, 0.0))  # a Modbus float register's NaN
    assert math.isnan(nan.tilt) and math.isnan(nan.tilt_direction)


def test_vibration_needs_ten_samples_in_the_last_second() -> None:
    window = VibrationWindow()
    still = Vector3(0.0, 0.0, 1.0)
    got = [window.add(i * 0.1, still) for i in range(12)]  # 10 Hz
    assert all(math.isnan(v) for v in got[:9])  # 9 samples: too few
    assert got[9:] == [0.0, 0.0, 0.0]  # a still sensor: 0, not NaN
    # a gap of more than a second empties the window: too few again
    assert math.isnan(window.add(5.0, still))
    slow = VibrationWindow()  # 5 Hz never has ten
    assert all(math.isnan(slow.add(i * 0.2, still)) for i in range(50))


def test_vibration_is_the_rms_of_the_magnitude_about_its_mean() -> None:
    window = VibrationWindow()
    got = math.nan
    for i in range(300):  # 100 Hz, the magnitude 1 ± 0.01 in turn, tilted to and fro
        m = 1.01 if i % 2 else 0.99
        tilt = math.radians(20.0 * math.sin(i / 10))
        got = window.add(i / 100, Vector3(m * math.sin(tilt), 0.0, m * math.cos(tilt)))
    assert got == 0.01  # the direction does not count, only the magnitude
    for i in range(300, 400):  # a step to 1.5 g: the window holds both sides of it
        got = window.add(i / 100, Vector3(0.0, 0.0, 1.5))
    assert got > 0.01
    got = window.add(4.0, Vector3(0.0, 0.0, 1.5))  # a second later, only the 1.5 g
    assert got == 0.0
    # NaN in a register is no sample; a clock that steps back starts again
    assert window.add(4.005, Vector3(math.nan, 0.0, 1.0)) == 0.0
    assert math.isnan(window.add(1.0, Vector3(0.0, 0.0, 1.0)))


def test_vibration_stays_exact_over_a_long_run() -> None:
    """The running sums are made again every thousand samples: after a day's worth of
    100 Hz noise the value equals the one summed from scratch."""
    rng = random.Random(7)
    window = VibrationWindow()
    kept: list[tuple[float, float]] = []
    got = math.nan
    for i in range(30_000):
        at, m = i / 100, 1.0 + rng.gauss(0.0, 0.02) + (5.0 if i % 997 == 0 else 0.0)
        got = window.add(at, Vector3(0.0, 0.0, m))
        kept = [(t, v) for t, v in kept if t >= at - 1.0] + [(at, m)]
    values = [v for _, v in kept]
    mean = sum(values) / len(values)
    assert got == round(math.sqrt(sum((v - mean) ** 2 for v in values) / len(values)), 4)


def test_derived_groups_follow_the_groups_of_the_reading() -> None:
    derive = Derivation()
    full = derive.complete(Reading(angles=Angles(3.0, 4.0, 0.0), accel=Vector3(0, 0, 1),
                                   gyro=Vector3(1, 2, 3)), at=1.0)
    assert full.tilt == Tilt(5.0, 126.92)
    assert full.vibration is not None and math.isnan(full.vibration.vibration)
    assert full.gyro == Vector3(1, 2, 3)
    imu = derive.complete(Reading(accel=Vector3(0, 0, 1)), at=1.01)  # no angles: no tilt
    assert imu.tilt is None and imu.vibration is not None
    gyro_only = Reading(gyro=Vector3(1, 2, 3))
    assert derive.complete(gyro_only, at=1.02) is gyro_only
    # each series has the derived groups of the groups it measures
    assert Group.TILT not in CAPABILITIES[Series.IMU].groups
    assert {Group.TILT, Group.VIBRATION} <= CAPABILITIES[Series.VG].groups
    assert CAPABILITIES[Series.AH].measured == MEASURED_GROUPS


def test_the_cache_completes_each_reading_once_for_every_listener() -> None:
    clock = [0.0]
    cache = Cache([("s", 1000.0)], clock=lambda: clock[0])
    seen: list[Snapshot] = []
    cache.subscribe(lambda kind, snap: seen.append(snap) if kind is EventKind.READING
                    else None)
    for i in range(12):  # 12 samples at 100 Hz of a still, tilted sensor
        cache.publish("s", Reading(angles=Angles(0.0, -30.0, 0.0),
                                   accel=Vector3(0.0, -0.5, 0.866)), at=i / 100)
    first, tenth = seen[0].reading, seen[9].reading
    assert first is not None and tenth is not None
    assert first.tilt == Tilt(30.0, 270.0)
    assert first.vibration is not None and math.isnan(first.vibration.vibration)
    assert tenth.vibration == Vibration(0.0)
    assert cache.snapshot("s").reading == seen[-1].reading
    assert seen[-1].to_json()["tilt"] == {"tilt": 30.0, "tilt_direction": 270.0}
    assert seen[0].to_json()["vibration"] == {"vibration": None}  # null, not 0


@pytest.mark.parametrize("moment", [
    datetime(2026, 11, 22, 3, 40, 0, 123456, tzinfo=UTC),
    datetime(2026, 11, 22, 3, 40, 0, tzinfo=UTC),  # (isoformat would drop no digits)
    datetime(2026, 12, 31, 23, 59, 59, 999999, tzinfo=UTC),  # (truncated, never rounded)
    datetime(2026, 3, 29, 1, 30, 0, 5000, tzinfo=ZoneInfo("Europe/Berlin")),
    datetime(2026, 1, 1, 0, 0, 0, 1000, tzinfo=timezone(timedelta(hours=-5))),
    datetime(1, 1, 1, 12, 0, 0, tzinfo=timezone(timedelta(hours=1))),
])
def test_iso_time_is_utc_in_milliseconds_with_a_z(moment: datetime) -> None:
    """The readings' time: the same as the format written out field by field."""
    utc = moment.astimezone(UTC)
    assert iso_time(moment) == (f"{utc.year:04d}-{utc.month:02d}-{utc.day:02d}T"
                                f"{utc.hour:02d}:{utc.minute:02d}:{utc.second:02d}."
                                f"{utc.microsecond // 1000:03d}Z")
    assert iso_time(None) is None
