"""Data answers of both protocols to the normalised ``Reading``.

Both protocol modules name the values they decode with the per-field names of the
reading JSON (``pitch``, ``accel_x``, ``q0`` …; ``model.VALUE_GROUPS``), so normalising
is one table from field name to (group, member) and no per-command code.

The derived groups (the tilt, the vibration) are worked out here too, but not on the
bus thread: the cache completes each reading as it enters it (``Derivation``), on the
main loop, once for every front end.  Sans-IO: time is an argument.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from typing import Any

from .model import (
    CAPABILITIES,
    VALUE_GROUPS,
    Angles,
    Group,
    Reading,
    Series,
    Tilt,
    Vector3,
    Vibration,
)

#: every per-field name, measured and derived, in the reading JSON's order
FIELD_NAMES: tuple[str, ...] = tuple(n for group in VALUE_GROUPS.values() for n in group.fields)


def member_name(group: Group, field_name: str) -> str:
    """``accel_x`` -> ``x``; angle and quaternion names are their own member names."""
    return field_name.split("_", 1)[1] if group in (Group.ACCEL, Group.GYRO, Group.MAG) \
        else field_name


def group_values(values: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """The measured values among ``values``, grouped as in the reading JSON.

    Partial groups stay partial (a 2.1 answer carries the pitch alone): this is the view
    for a person reading one frame; ``to_reading`` is the one for the cache.
    """
    out: dict[str, dict[str, float]] = {}
    for group, spec in VALUE_GROUPS.items():
        members = {member_name(group, n): float(values[n]) for n in spec.fields if n in values}
        if members:
            out[group.value] = members
    return out


#: series -> (reading attribute, its dataclass, per-field names) of each group the
#: series measures: ``to_reading``'s table, worked out once (it runs for every answer).
_MEASURED: dict[Series, tuple[tuple[str, type, tuple[str, ...]], ...]] = {
    series: tuple((group.value, spec.type, spec.fields) for group, spec in VALUE_GROUPS.items()
                  if group in caps.measured)
    for series, caps in CAPABILITIES.items()
}


#: series -> the per-field names it gives (measured, and derived from those), in the
#: reading JSON's order.
MEASURED_FIELDS: dict[Series, tuple[str, ...]] = {
    series: tuple(n for group, spec in VALUE_GROUPS.items() if group in caps.groups
                  for n in spec.fields)
    for series, caps in CAPABILITIES.items()
}


def to_reading(values: Mapping[str, Any], series: Series) -> Reading | None:
    """A ``Reading`` from decoded values, or ``None`` if they measure nothing.

    Only whole groups are kept: a group the answer covers in part (a 2.1 answer has
    the pitch alone) is left out rather than completed from an older reading, because
    an old value under a new timestamp would lie about its age.  Groups the series
    does not measure are dropped too: a Modbus VG leaves the magnetometer registers
    at zero, which is "not measured", not "zero gauss".
    """
    groups: dict[str, Any] = {}
    for key, cls, names in _MEASURED[series]:
        try:
            groups[key] = cls(*[float(values[n]) for n in names])
        except KeyError:
            continue  # (a group the answer covers in part, or not at all)
    return Reading(**groups) if groups else None


#: (reading attribute, ((per-field name, member name), …)) of every group: the table of
#: ``field_values``, worked out once (it runs for every reading the history keeps).
_FIELDS_OF: tuple[tuple[str, tuple[tuple[str, str], ...]], ...] = tuple(
    (group.value, tuple((n, member_name(group, n)) for n in spec.fields))
    for group, spec in VALUE_GROUPS.items()
)


def field_values(reading: Reading) -> dict[str, float]:
    """The inverse view: a reading's measured values by per-field name."""
    out: dict[str, float] = {}
    for attribute, names in _FIELDS_OF:
        value = getattr(reading, attribute)
        if value is not None:
            for name, member in names:
                out[name] = getattr(value, member)
    return out


# ------------------------------------------------------------------ derived values

_NAN = math.nan
_TILT_DIGITS = VALUE_GROUPS[Group.TILT].digits
_VIBRATION_DIGITS = VALUE_GROUPS[Group.VIBRATION].digits


def tilt_of(angles: Angles) -> Tilt:
    """The tilt from vertical, ``acos(cos(pitch)·cos(roll))``, and the azimuth of the
    lean in the sensor's frame: the direction of gravity's component in its x-y plane
    (body axes x forward, y right, z down; gravity there is (-sin θ, sin φ·cos θ,
    cos φ·cos θ)), 0° toward +x, 90° toward +y.  Where the tilt rounds to 0 there is
    no lean to point at: the direction is NaN (null), not a made-up 0."""
    pitch, roll = math.radians(angles.pitch), math.radians(angles.roll)
    if not (math.isfinite(pitch) and math.isfinite(roll)):
        return Tilt(_NAN, _NAN)  # (a Modbus float register can hold NaN)
    cos_pitch = math.cos(pitch)
    # clamped: a product of rounded cosines may stray past 1 by an ulp (acos then fails)
    level = max(-1.0, min(1.0, cos_pitch * math.cos(roll)))
    tilt = round(math.degrees(math.acos(level)), _TILT_DIGITS)
    if tilt == 0.0:
        return Tilt(0.0, _NAN)
    azimuth = math.degrees(math.atan2(math.sin(roll) * cos_pitch, -math.sin(pitch)))
    direction = round(azimuth % 360.0, _TILT_DIGITS)
    return Tilt(tilt, 0.0 if direction >= 360.0 else direction)  # (359.999 rounds to 360)


class VibrationWindow:
    """One sensor's acceleration magnitudes of the last ``SPAN_S`` (by receive time),
    and the RMS of their deviation from their mean (g): NaN while the window holds
    fewer than ``LEAST`` samples, too few for an RMS that means anything.

    The sums are kept as samples come and go (a 100 Hz sensor's window is 100 samples:
    summing them anew for each would cost more than everything else a sample costs), of
    each magnitude minus ``_shift`` (a recent magnitude: the deviations are small, so
    the sum of squares loses no digits), and are made again exactly every
    ``_EXACT_EVERY`` samples so rounding errors cannot pile up over a long run.
    """

    SPAN_S = 1.0
    LEAST = 10
    _EXACT_EVERY = 1000

    def __init__(self) -> None:
        self._kept: deque[tuple[float, float]] = deque()  # (at, magnitude)
        self._shift = 0.0
        self._sum = 0.0
        self._squares = 0.0
        self._added = 0

    def add(self, at: float, accel: Vector3) -> float:
        """A sample received at ``at`` (seconds, monotonic); returns the vibration now."""
        kept = self._kept
        if kept and at < kept[-1][0]:
            kept.clear()  # the clock went back: what was kept is of another time line
        magnitude = math.sqrt(accel.x * accel.x + accel.y * accel.y + accel.z * accel.z)
        if math.isfinite(magnitude):  # (NaN in a Modbus float register: no sample)
            if not kept:
                self._shift, self._sum, self._squares = magnitude, 0.0, 0.0
            kept.append((at, magnitude))
            d = magnitude - self._shift
            self._sum += d
            self._squares += d * d
        cut = at - self.SPAN_S
        while kept and kept[0][0] < cut:
            d = kept.popleft()[1] - self._shift
            self._sum -= d
            self._squares -= d * d
        self._added += 1
        if self._added >= self._EXACT_EVERY:
            self._exact()
        n = len(kept)
        if n < self.LEAST:
            return _NAN
        mean = self._sum / n
        return round(math.sqrt(max(0.0, self._squares / n - mean * mean)), _VIBRATION_DIGITS)

    def _exact(self) -> None:
        self._added = 0
        if self._kept:
            self._shift = self._kept[-1][1]
            self._sum = math.fsum(m - self._shift for _, m in self._kept)
            self._squares = math.fsum((m - self._shift) ** 2 for _, m in self._kept)


class Derivation:
    """One sensor's derived values: ``complete`` adds them to each of its readings."""

    def __init__(self) -> None:
        self.window = VibrationWindow()

    def complete(self, reading: Reading, at: float) -> Reading:
        """``reading`` with its derived groups, received at ``at`` (monotonic seconds):
        the tilt where it has angles, the vibration where it has accelerations."""
        angles, accel = reading.angles, reading.accel
        if angles is None and accel is None:
            return reading
        return Reading(
            angles=angles, accel=accel, gyro=reading.gyro, mag=reading.mag,
            quaternion=reading.quaternion,
            tilt=tilt_of(angles) if angles is not None else None,
            vibration=Vibration(self.window.add(at, accel)) if accel is not None else None)
