"""The angle arguments of the command catalogue (``imu_gateway.commands``): the ranges the
sensors' formats carry, and rounding to their resolution before the range is checked.

Native 2.20 sends the relative heading as SXXX.YY (signed, 0.01), 2.21 the declination
as SXX.Y (signed, 0.1).  Every front end validates through the same models.
"""

from __future__ import annotations

import math
from typing import Any

import pytest

from imu_gateway.commands import validate
from imu_gateway.errors import ErrorKind, RequestFailed
from imu_gateway.model import Series, WireProtocol


def degrees(name: str, value: Any, series: Series,
            protocol: WireProtocol = WireProtocol.NATIVE) -> Any:
    return validate(name, {"degrees": value}, series, protocol).args["degrees"]


@pytest.mark.parametrize(("given", "sent"), [
    (-45.5, -45.5), (-999.99, -999.99), (999.99, 999.99), (359.999, 360.0), (0, 0.0),
    (1.005, 1.01), (-1.005, -1.01), (-0.005, -0.01),
])
def test_relative_heading_takes_the_whole_signed_range(given: float, sent: float) -> None:
    """SXXX.YY has a sign: a negative start point is a value the sensor can hold."""
    assert degrees("set_relative_heading", given, Series.MINS) == sent
    assert degrees("set_relative_heading", given, Series.MINS, WireProtocol.MODBUS) == sent


@pytest.mark.parametrize(("given", "sent"), [
    (0.25, 0.3), (-0.25, -0.3), (0.15, 0.2), (1.25, 1.3), (-1.25, -1.3), (0.24, 0.2),
    (99.9, 99.9), (-99.9, -99.9), (99.94, 99.9),
    (99.90000152587891, 99.9), (-99.90000152587891, -99.9),  # the float32s of ±99.9
])
def test_declination_rounds_half_away_from_zero_then_checks_the_range(
        given: float, sent: float) -> None:
    assert degrees("set_declination", given, Series.AH) == sent


@pytest.mark.parametrize(("name", "series", "value"), [
    ("set_declination", Series.AH, 99.95),  # rounds to 100.0: beyond SXX.Y
    ("set_declination", Series.AH, -100),
    ("set_declination", Series.AH, math.nan),
    ("set_declination", Series.AH, math.inf),
    ("set_declination", Series.AH, "5"),
    ("set_declination", Series.AH, True),
    ("set_relative_heading", Series.MINS, 999.995),  # rounds to 1000.00
    ("set_relative_heading", Series.MINS, -1000),
    ("set_relative_heading", Series.MINS, -math.inf),
    ("set_relative_heading", Series.MINS, None),
])
def test_values_beyond_the_format_or_not_numbers_are_refused(name: str, series: Series,
                                                             value: Any) -> None:
    with pytest.raises(RequestFailed) as caught:
        degrees(name, value, series)
    assert caught.value.kind is ErrorKind.BAD_ARGUMENTS
