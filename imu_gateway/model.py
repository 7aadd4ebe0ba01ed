"""The normalised model every part of the gateway speaks: series, readings, capabilities.

Units: degrees for angles, g for acceleration, deg/s for angular rate, gauss for the
magnetic field, a unit quaternion (q0 the scalar part).  Those are the sensors' own
units in both protocols, so no conversion happens between the wire and a client.

Two groups are derived, never decoded from a frame: the tilt (from the angles' pitch
and roll) and the vibration (from the acceleration), worked out by the cache as a
reading enters it (``normalise.Derivation``; docs/alarms.md, "Derived values").
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from types import MappingProxyType
from typing import Any


class Series(enum.Enum):
    """Sensor families.  The value is the code of the Modbus TCP map's register 6."""

    IMU = 1
    VG = 2
    AH = 3
    MINS = 4


class WireProtocol(enum.Enum):
    """What the sensor speaks on the serial line.  The value is register 7's code."""

    NATIVE = 0
    MODBUS = 1


class Group(enum.Enum):
    """The value groups of a reading, named as in the reading JSON (docs/mqtt.md)."""

    ANGLES = "angles"
    ACCEL = "accel"
    GYRO = "gyro"
    MAG = "mag"
    QUATERNION = "quaternion"
    TILT = "tilt"  # derived (from ANGLES)
    VIBRATION = "vibration"  # derived (from ACCEL)


@dataclass(frozen=True, slots=True)
class Angles:
    pitch: float
    roll: float
    yaw: float


@dataclass(frozen=True, slots=True)
class Vector3:
    x: float
    y: float
    z: float


@dataclass(frozen=True, slots=True)
class Quaternion:
    q0: float
    q1: float
    q2: float
    q3: float


@dataclass(frozen=True, slots=True)
class Tilt:
    """The inclination from vertical and the azimuth of the lean (docs/alarms.md);
    ``tilt_direction`` is NaN (null in JSON) where the tilt is 0 and it has none."""

    tilt: float
    tilt_direction: float


@dataclass(frozen=True, slots=True)
class Vibration:
    """The RMS of the acceleration magnitude's deviation from its mean over the last
    second; NaN (null in JSON) while that second holds too few samples to tell."""

    vibration: float


_XYZ = ("x", "y", "z")


@dataclass(frozen=True, slots=True)
class ValueGroup:
    """One value group, the one place for it: its dataclass, the per-field names of its
    members in order (the reading JSON's and the Modbus TCP map's), and how its values
    are told.  ``symbol`` is what the register map, Home Assistant and the dashboard
    show, ``name`` what the API descriptions say, and ``digits`` the decimals the
    documents give its values (the BCD formats' and the Modbus registers' resolution),
    which is also the integer registers' scale (``10 ** digits``).  ``title`` names
    the group where a tree shows it (Sparkplug's metric folders, OPC UA's); ``span``
    is the largest magnitude the native protocol's format can carry (OPC UA's
    EURange).  ``derived_from``: the groups a derived group is worked out from (empty
    for a measured one): a series has it when it measures all of them."""

    type: type[Angles | Vector3 | Quaternion | Tilt | Vibration]
    fields: tuple[str, ...]
    symbol: str
    name: str
    digits: int
    title: str
    span: float
    derived_from: frozenset[Group] = frozenset()

    @property
    def scale(self) -> int:
        return int(10**self.digits)

    @property
    def derived(self) -> bool:
        return bool(self.derived_from)


#: The value groups, one row each.  The units are the sensors' own in both protocols
#: (the module docstring says why there is no conversion).
VALUE_GROUPS: Mapping[Group, ValueGroup] = MappingProxyType({
    Group.ANGLES: ValueGroup(Angles, ("pitch", "roll", "yaw"), "°", "degrees", 2, "Angles",
                             999.99),
    Group.ACCEL: ValueGroup(Vector3, tuple(f"accel_{a}" for a in _XYZ), "g",
                            "standard gravity (g)", 4, "Acceleration", 9.9999),
    Group.GYRO: ValueGroup(Vector3, tuple(f"gyro_{a}" for a in _XYZ), "°/s",
                           "degrees per second", 2, "AngularRate", 999.99),
    Group.MAG: ValueGroup(Vector3, tuple(f"mag_{a}" for a in _XYZ), "G", "gauss", 5,
                          "MagneticField", 0.99999),
    Group.QUATERNION: ValueGroup(Quaternion, ("q0", "q1", "q2", "q3"), "", "unitless", 6,
                                 "Quaternion", 9.999999),
    # Derived (docs/alarms.md): the tilt is 0-180°, its direction 0-360°; the vibration
    # is at most the largest magnitude three accelerations of 9.9999 g make.
    Group.TILT: ValueGroup(Tilt, ("tilt", "tilt_direction"), "°", "degrees", 2, "Tilt",
                           360.0, frozenset({Group.ANGLES})),
    Group.VIBRATION: ValueGroup(Vibration, ("vibration",), "g", "standard gravity (g)", 4,
                                "Vibration", 17.3203, frozenset({Group.ACCEL})),
})

#: The groups decoded from frames, and those the cache works out from them.
MEASURED_GROUPS = frozenset(g for g, spec in VALUE_GROUPS.items() if not spec.derived)
DERIVED_GROUPS = frozenset(g for g, spec in VALUE_GROUPS.items() if spec.derived)


@dataclass(frozen=True, slots=True)
class Reading:
    """One sample.  A group the answer did not carry is ``None`` (absent, not zero)."""

    angles: Angles | None = None
    accel: Vector3 | None = None
    gyro: Vector3 | None = None
    mag: Vector3 | None = None
    quaternion: Quaternion | None = None
    tilt: Tilt | None = None  # derived: filled by the cache (``normalise.Derivation``)
    vibration: Vibration | None = None  # derived likewise

    def groups(self) -> frozenset[Group]:
        return frozenset(g for g in Group if getattr(self, g.value) is not None)

    def only(self, groups: frozenset[Group]) -> Reading:
        """The same reading with every group outside ``groups`` dropped."""
        return Reading(**{g.value: getattr(self, g.value) for g in groups})

    def to_json_groups(self) -> dict[str, dict[str, float | None]]:
        """The value groups of the reading JSON (docs/mqtt.md), absent groups left out.
        A value that is not a finite number (a Modbus float register can hold NaN) is
        ``None``: JSON has no NaN, and one would break every client's parser."""
        out: dict[str, dict[str, float | None]] = {}
        isfinite = math.isfinite
        for key, members in _JSON_GROUPS:
            value: Any = getattr(self, key)
            if value is not None:
                out[key] = {name: v if isfinite(v := getattr(value, name)) else None
                            for name in members}
        return out


#: (group key, its dataclass's member names) of every group, in order: the table of
#: ``to_json_groups``, worked out once (the reading JSON is made for every sample a
#: front end pushes; ``dataclasses.fields`` per group cost MQTT 6 of its 69 µs a
#: sample, warm)
_JSON_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = tuple(
    (group.value, tuple(f.name for f in fields(spec.type)))
    for group, spec in VALUE_GROUPS.items()
)


#: A float32's bytes (little-endian), and the formats tried for its shortest decimal.
_FLOAT32 = struct.Struct("<f")
_DIGITS = {digits: f"%.{digits}g" for digits in range(6, 10)}
#: float32s from here up have rounding intervals whose ends can be short decimals.
_SHORT_ENDS = 2.0**24


def shortest_float32(value: float) -> float:
    """A float32 (widened to a Python float) as the shortest decimal that is the same
    float32: 0.011224, not 0.011223999783396721; 99.9, not 99.90000152587891.

    A float32 holds about seven digits and the rest is noise of the widening, so this
    is the number the sender meant, whether a sensor's register (Modbus RTU) or a
    client's write (Modbus TCP) carried it.

    It runs for every float of every Modbus answer, so it tries two roundings, not
    up to four: where the decimals that are the same float32 lie evenly around it
    (not a power of two, below 2**24), a rounding to k digits that is the same float32
    means the rounding to k + 1 digits is too (it is nearer), so 7 digits decide
    between 6-7 and 8-9.  Elsewhere every count is tried in turn, shortest first.
    """
    if not math.isfinite(value):
        return value
    packed = _FLOAT32.pack(value)
    if int.from_bytes(packed, "little") & 0x7FFFFF and abs(value) < _SHORT_ENDS:
        seven = float(_DIGITS[7] % value)
        if _FLOAT32.pack(seven) == packed:
            six = float(_DIGITS[6] % value)
            return six if _FLOAT32.pack(six) == packed else seven
        eight = float(_DIGITS[8] % value)
        return eight if _FLOAT32.pack(eight) == packed else float(_DIGITS[9] % value)
    for digits in range(6, 10):
        shortest = float(_DIGITS[digits] % value)
        if _FLOAT32.pack(shortest) == packed:
            return shortest
    return value  # pragma: no cover - nine significant digits always round-trip


@dataclass(frozen=True, slots=True)
class Capabilities:
    """What a series gives: ``groups``, the groups it measures and those derived from
    them.  (Which commands it has is the command catalogue's business:
    ``commands.CATALOGUE``, one row per command.)"""

    groups: frozenset[Group]

    @classmethod
    def measuring(cls, *measured: Group) -> Capabilities:
        """The series that measures ``measured``, with every group derived from them."""
        have = frozenset(measured)
        return cls(have | {g for g in DERIVED_GROUPS if VALUE_GROUPS[g].derived_from <= have})

    @property
    def measured(self) -> frozenset[Group]:
        """The groups its frames carry."""
        return self.groups & MEASURED_GROUPS


# The one table of per-series capabilities.  The native document says which series
# answer which data command (2.13-2.15, 2.19-2.26); the Modbus map is the same for all
# series, and a series simply leaves the registers it lacks at zero.
CAPABILITIES: Mapping[Series, Capabilities] = MappingProxyType({
    Series.IMU: Capabilities.measuring(Group.ACCEL, Group.GYRO),
    Series.VG: Capabilities.measuring(Group.ANGLES, Group.ACCEL, Group.GYRO, Group.QUATERNION),
    Series.AH: Capabilities.measuring(*MEASURED_GROUPS),
    Series.MINS: Capabilities.measuring(Group.ANGLES, Group.ACCEL, Group.GYRO, Group.QUATERNION),
})


@dataclass(frozen=True, slots=True)
class KnownSettings:
    """A sensor's settings as far as the gateway knows them: learned from the answers
    to commands and pass-through exchanges, never guessed (``None``: not known).  The
    same type says what one answer *shows* (``None``: it says nothing of that one)."""

    zero_type: str | None = None
    declination: float | None = None
    relative_heading: float | None = None
    mag_calibration: str | None = None
    busy_with: str | None = None  # the save or gyro calibration under way

    def updated(self, shown: KnownSettings) -> KnownSettings:
        """These settings, with what ``shown`` knows taking the place of the old."""
        changes: dict[str, Any] = shown.to_json()
        return replace(self, **changes)

    def to_json(self) -> dict[str, str | float]:
        """The known ones only, as REST shows them."""
        return {f.name: value for f in fields(self)
                if (value := getattr(self, f.name)) is not None}
