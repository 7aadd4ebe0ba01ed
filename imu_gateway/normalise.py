"""Data answers of both protocols to the normalised ``Reading``.

Both protocol modules name the values they decode with the per-field names of the
reading JSON (``pitch``, ``accel_x``, ``q0`` …; ``model.VALUE_GROUPS``), so normalising
is one table from field name to (group, member) and no per-command code.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from .model import CAPABILITIES, VALUE_GROUPS, Group, Reading, Series

#: every per-field name, in the reading JSON's order
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
                  if group in caps.groups)
    for series, caps in CAPABILITIES.items()
}


#: series -> the per-field names it measures, in the reading JSON's order.
MEASURED_FIELDS: dict[Series, tuple[str, ...]] = {
    series: tuple(n for _, _, names in groups for n in names)
    for series, groups in _MEASURED.items()
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
