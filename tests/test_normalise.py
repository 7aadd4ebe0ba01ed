"""Decoded values to the normalised ``Reading`` (``imu_gateway.normalise``).

A reading carries exactly the groups the series measures (``model.CAPABILITIES``),
whichever protocol the values came from; partial groups are left out; the AH
example of the native document gives exactly the value groups of the example reading JSON
in docs/mqtt.md.
"""

from __future__ import annotations

import pytest
from support.vectors import ANSWER, NATIVE_VECTORS, Vector

from imu_gateway.model import CAPABILITIES, Angles, Group, Quaternion, Reading, Series, Vector3
from imu_gateway.normalise import FIELD_NAMES, group_values, to_reading
from imu_gateway.protocol import modbus_rtu as rtu
from imu_gateway.protocol import native

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
    assert reading.groups() == CAPABILITIES[series].groups


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
    assert set(read) == set(FIELD_NAMES)
    vg = to_reading(read, Series.VG)
    assert vg is not None
    assert vg.mag is None
    assert vg.groups() == CAPABILITIES[Series.VG].groups
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
