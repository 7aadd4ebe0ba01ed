"""The derived values (docs/alarms.md, "Derived values") as the tests expect them,
written out here from the document rather than taken from the gateway, and a reading
whose values a native sensor carries exactly."""

from __future__ import annotations

import math
from dataclasses import replace

from imu_gateway.model import Angles, Reading, Vector3
from imu_gateway.simulator.motion import Motion

#: Decimals a native sensor's BCD carries exactly (32.52 is 32.52 on the wire), a
#: float32 does not (32.52000045776367), and a still sensor's acceleration (vibration 0).
EXACT = replace(Motion.from_seed(5).sample(2.0), angles=Angles(32.52, -3.5, 100.25),
                accel=Vector3(-0.5373, -0.0494, 0.842))


def tilt(pitch: float, roll: float) -> tuple[float, float | None]:
    """(tilt, tilt_direction) of docs/alarms.md, to two decimals; no direction when level."""
    p, r = math.radians(pitch), math.radians(roll)
    angle = round(math.degrees(math.acos(max(-1.0, min(1.0, math.cos(p) * math.cos(r))))), 2)
    if angle == 0:
        return 0.0, None
    direction = round(math.degrees(math.atan2(math.sin(r) * math.cos(p), -math.sin(p))) % 360, 2)
    return angle, 0.0 if direction == 360 else direction


def exact_tilt(reading: Reading = EXACT) -> tuple[float, float | None]:
    assert reading.angles is not None
    return tilt(reading.angles.pitch, reading.angles.roll)
