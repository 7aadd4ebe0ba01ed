"""The simulated sensor's motion: a smooth, deterministic trajectory and the readings it gives.

A sensor on a slowly moving machine (think crane boom): roll and pitch sway sinusoidally, yaw
turns at a constant rate.  Every group of a reading is derived from the same three Euler angles
(aerospace ZYX: yaw ψ, then pitch θ, then roll φ; body axes x forward, y right, z down; the
world frame is north-east-down), so accel, gyro, mag and quaternion agree with each other.
Pure functions of ``t``: no clock, no global state.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from typing import Protocol

from imu_gateway.model import Angles, Quaternion, Reading, Vector3

TAU = 2.0 * math.pi
#: The Earth's field (gauss): north, and dipping down, as in mid-northern latitudes.
MAG_NORTH, MAG_DOWN = 0.2, 0.42


class Source(Protocol):
    """Anything the simulator can ask for the reading at time ``t`` (seconds)."""

    def sample(self, t: float) -> Reading: ...


def _to_body(v: tuple[float, float, float], roll: float, pitch: float, yaw: float) -> Vector3:
    """A north-east-down vector expressed in body axes: Rx(φ)ᵀ·Ry(θ)ᵀ·Rz(ψ)ᵀ·v (radians)."""
    cf, sf = math.cos(roll), math.sin(roll)
    ct, st = math.cos(pitch), math.sin(pitch)
    cp, sp = math.cos(yaw), math.sin(yaw)
    x1, y1, z1 = cp * v[0] + sp * v[1], -sp * v[0] + cp * v[1], v[2]
    x2, z2 = ct * x1 - st * z1, st * x1 + ct * z1
    return Vector3(x2, cf * y1 + sf * z2, -sf * y1 + cf * z2)


@dataclass(frozen=True, slots=True)
class Motion:
    """roll = A·sin(2π f t + φ), pitch likewise, yaw = yaw0 + rate·t wrapped to [0, 360).

    Amplitudes and angles in degrees, frequencies in Hz, phases in radians.  The Earth field
    (gauss) points north and dips down, as in mid-northern latitudes.
    """

    roll_amp: float = 20.0
    pitch_amp: float = 12.0
    roll_freq: float = 0.1
    pitch_freq: float = 0.07
    roll_phase: float = 0.0
    pitch_phase: float = 0.0
    yaw0: float = 0.0
    yaw_rate: float = 6.0
    mag_north: float = MAG_NORTH
    mag_down: float = MAG_DOWN

    @classmethod
    def from_seed(cls, seed: int) -> Motion:
        """Varied but deterministic parameters, so several simulated sensors differ."""
        rng = random.Random(seed)
        return cls(
            roll_amp=rng.uniform(5.0, 30.0),
            pitch_amp=rng.uniform(3.0, 20.0),  # well clear of the ±90° gimbal lock
            roll_freq=rng.uniform(0.05, 0.2),
            pitch_freq=rng.uniform(0.05, 0.2),
            roll_phase=rng.uniform(0.0, TAU),
            pitch_phase=rng.uniform(0.0, TAU),
            yaw0=rng.uniform(0.0, 360.0),
            yaw_rate=rng.choice((-1.0, 1.0)) * rng.uniform(2.0, 10.0),
        )

    def yaw(self, t: float) -> float:
        """The heading at ``t``, wrapped to [0, 360)."""
        yaw = (self.yaw0 + self.yaw_rate * t) % 360.0
        return 0.0 if yaw >= 360.0 else yaw  # a tiny negative value rounds up to 360.0 under %

    def sway(self, t: float) -> tuple[float, float, float, float]:
        """Roll, pitch and their analytic rates (degrees, deg/s) at ``t``."""
        wr, wp = TAU * self.roll_freq, TAU * self.pitch_freq
        return (self.roll_amp * math.sin(wr * t + self.roll_phase),
                self.pitch_amp * math.sin(wp * t + self.pitch_phase),
                self.roll_amp * wr * math.cos(wr * t + self.roll_phase),
                self.pitch_amp * wp * math.cos(wp * t + self.pitch_phase))

    def sample(self, t: float) -> Reading:
        roll, pitch, droll, dpitch = self.sway(t)
        return attitude(Angles(pitch, roll, self.yaw(t)), (droll, dpitch, self.yaw_rate),
                        (self.mag_north, self.mag_down))


def attitude(angles: Angles, rates: tuple[float, float, float],
             field: tuple[float, float] = (MAG_NORTH, MAG_DOWN)) -> Reading:
    """The whole reading of a sensor at ``angles`` whose roll, pitch and yaw change at
    ``rates`` (deg/s), in an Earth field of ``field`` (north, down; gauss): every group
    from the same three angles."""
    droll, dpitch, dyaw = rates
    # The trigonometry works in radians.
    f, th, ps = math.radians(angles.roll), math.radians(angles.pitch), math.radians(angles.yaw)
    cf, sf, ct, st = math.cos(f), math.sin(f), math.cos(th), math.sin(th)
    gyro = Vector3(  # body rates p, q, r from the ZYX kinematic equations
        droll - dyaw * st,
        dpitch * cf + dyaw * ct * sf,
        -dpitch * sf + dyaw * ct * cf,
    )
    # The sensors report gravity's direction in their own frame, +1 g on z when level
    # (the documents' examples), i.e. the NED "down" unit vector in body axes.
    accel = _to_body((0.0, 0.0, 1.0), f, th, ps)
    mag = _to_body((field[0], 0.0, field[1]), f, th, ps)
    return Reading(angles=angles, accel=accel, gyro=gyro, mag=mag,
                   quaternion=_quaternion(f, th, ps))


def _quaternion(roll: float, pitch: float, yaw: float) -> Quaternion:
    """Body-to-NED rotation q = qz(ψ)⊗qy(θ)⊗qx(φ), unit length, sign chosen so q0 ≥ 0."""
    cf, sf = math.cos(roll / 2), math.sin(roll / 2)
    ct, st = math.cos(pitch / 2), math.sin(pitch / 2)
    cp, sp = math.cos(yaw / 2), math.sin(yaw / 2)
    q = (
        cf * ct * cp + sf * st * sp,
        sf * ct * cp - cf * st * sp,
        cf * st * cp + sf * ct * sp,
        cf * ct * sp - sf * st * cp,
    )
    n = math.copysign(math.sqrt(sum(c * c for c in q)), q[0])  # q and -q are the same rotation
    return Quaternion(q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@dataclass(frozen=True, slots=True)
class Fixed:
    """A source that always gives the same reading (e.g. a document's example values)."""

    reading: Reading

    def sample(self, t: float) -> Reading:
        return self.reading


def hold(reading: Reading) -> Fixed:
    return Fixed(reading)


#: The lean's limits (degrees).  Pitch stops short of ±90°, where roll and yaw become
#: one rotation (gimbal lock) and the Euler angles a sensor reports lose their meaning.
PITCH_LIMIT, ROLL_LIMIT = 89.0, 180.0


@dataclass(frozen=True, slots=True)
class Leaned:
    """``base`` held at a fixed pitch and roll (degrees), exactly: a machine leaning
    and standing still there.  The heading goes on as ``base`` has it (a ``Motion``
    keeps turning at its yaw rate, and the gyro shows that turn at the lean), and
    every group is worked out from the same three angles, as ``Motion``'s are."""

    base: Source
    pitch: float
    roll: float

    def __post_init__(self) -> None:
        for name, value, limit in (("pitch", self.pitch, PITCH_LIMIT),
                                   ("roll", self.roll, ROLL_LIMIT)):
            if not -limit <= value <= limit:  # NaN fails this too
                raise ValueError(f"a lean's {name} is a number of degrees from {-limit:g} "
                                 f"to {limit:g}, not {value!r}")

    def sample(self, t: float) -> Reading:
        if isinstance(self.base, Motion | Turned):
            yaw, rate = self.base.yaw(t), self.base.yaw_rate
            field = (self.base.mag_north, self.base.mag_down)
        else:  # a still source: its heading, if it has one
            angles = self.base.sample(t).angles
            yaw, rate, field = (angles.yaw if angles else 0.0), 0.0, (MAG_NORTH, MAG_DOWN)
        return attitude(Angles(float(self.pitch), float(self.roll), yaw), (0.0, 0.0, rate),
                        field)


@dataclass(frozen=True, slots=True)
class Turned:
    """``base`` turned to a heading: ``yaw0`` (degrees) at ``since`` (the simulator's
    clock, seconds), turning on at ``rate`` deg/s from there (0: held), as a person
    turns a sensor in their hand.  Pitch and roll go on as ``base`` has them, and every
    group follows the heading: the Earth's field turns in the sensor's frame, so mag x
    against mag y draws a circle as the heading goes round."""

    base: Source
    yaw0: float
    rate: float = 0.0
    since: float = 0.0

    def __post_init__(self) -> None:
        for name, value in (("heading", self.yaw0), ("rate", self.rate)):
            if not math.isfinite(value) or abs(value) > 3600.0:
                raise ValueError(f"a turn's {name} is a number of degrees (per second) from "
                                 f"-3600 to 3600, not {value!r}")

    @property
    def yaw_rate(self) -> float:
        return self.rate

    @property
    def mag_north(self) -> float:
        return self.base.mag_north if isinstance(self.base, Motion) else MAG_NORTH

    @property
    def mag_down(self) -> float:
        return self.base.mag_down if isinstance(self.base, Motion) else MAG_DOWN

    def yaw(self, t: float) -> float:
        yaw = (self.yaw0 + self.rate * (t - self.since)) % 360.0
        return 0.0 if yaw >= 360.0 else yaw

    def sample(self, t: float) -> Reading:
        if isinstance(self.base, Motion):
            roll, pitch, droll, dpitch = self.base.sway(t)
        else:  # a still source: its pitch and roll, held
            angles = self.base.sample(t).angles
            roll, pitch = (angles.roll, angles.pitch) if angles else (0.0, 0.0)
            droll = dpitch = 0.0
        return attitude(Angles(pitch, roll, self.yaw(t)), (droll, dpitch, self.rate),
                        (self.mag_north, self.mag_down))
