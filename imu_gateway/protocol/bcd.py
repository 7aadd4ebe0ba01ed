"""Packed BCD with a sign nibble, as the native protocol sends every measured value.

A value is a run of nibbles: first the sign (0 positive, 1 negative), then the
integer digits, then the decimal digits; two nibbles to a byte, high nibble first.
The document writes the formats as patterns; ``SXXX.YY`` means one sign nibble,
three integer digits and two decimal digits, packed in three bytes:

    10 34 63  ->  sign 1, digits 034, 63  ->  -34.63

The formats differ only in their digit counts, so they are one table of
``BcdFormat`` rows rather than one function each.  Values are kept as integer
*counts* of the last digit internally so that decoding is exact and a round trip
never drifts by a float ulp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from decimal import ROUND_HALF_UP, Decimal

from .errors import BadBcd, BadLength, UsageError

#: Stands in for a byte with a nibble above 9 in ``_PAIRS``: so negative that the
#: magnitude it is folded into stays negative whatever digits follow (up to 18 digits).
_NOT_DECIMAL = -(10**20)
#: Every byte's two nibbles read as two decimal digits (0x47 -> 47), or ``_NOT_DECIMAL``.
#: Decoding is then one lookup per byte: a value is decoded hundreds of times a second.
_PAIRS: tuple[int, ...] = tuple(
    (b >> 4) * 10 + (b & 0x0F) if b >> 4 <= 9 and b & 0x0F <= 9 else _NOT_DECIMAL
    for b in range(256)
)


def round_half_away(value: float, digits: int) -> int:
    """``value`` in units of 10**-``digits``, rounded half away from zero.

    A sensor's display rounds 0.25 to one decimal as 0.3 and -0.25 as -0.3; Python's
    ``round`` gives 0.2 (half to even), and ``1.005 * 100`` is 100.49999…, which no
    rounding of the product can take to 101.  A half is therefore decided on the
    decimal the float was written as (its shortest ``repr``).  Only values within a
    hair of a half take that slower path: the simulator encodes thousands a second.
    """
    scaled = value * 10**digits
    if not math.isfinite(scaled):
        raise UsageError(f"{value} cannot be rounded to {digits} decimals")
    counts = round(scaled)
    if abs(abs(scaled - counts) - 0.5) < 1e-6:
        exact = Decimal(repr(value)).scaleb(digits)
        counts = int(exact.to_integral_value(rounding=ROUND_HALF_UP))  # halves away from 0
    return int(counts)


@dataclass(frozen=True, slots=True)
class BcdFormat:
    """One packed-BCD value layout: a sign nibble, then integer and decimal digits."""

    name: str
    int_digits: int
    frac_digits: int
    #: Bytes on the wire: the sign nibble and every digit, two nibbles to a byte.
    size: int = field(init=False, repr=False, compare=False)
    #: Counts of the last digit per unit: 100 for ``SXXX.YY``.
    scale: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Worked out once: they are read for every value decoded.
        object.__setattr__(self, "size", (1 + self.int_digits + self.frac_digits) // 2)
        object.__setattr__(self, "scale", int(10**self.frac_digits))

    @property
    def max_counts(self) -> int:
        """The largest magnitude expressible, in units of the last decimal digit."""
        return int(10 ** (self.int_digits + self.frac_digits)) - 1

    @property
    def max_value(self) -> float:
        return self.max_counts / self.scale

    @property
    def resolution(self) -> float:
        return 1 / self.scale

    def encode(self, value: float) -> bytes:
        """Encode ``value`` rounded to this format's resolution, halves away from zero
        (``round_half_away``).

        Raises ``UsageError`` when the rounded magnitude does not fit (or is not finite).
        """
        if not math.isfinite(value):
            raise UsageError(f"{value} cannot be sent as BCD {self.name}")
        return self.encode_counts(round_half_away(value, self.frac_digits))

    def rounded(self, value: float) -> float:
        """``value`` at this format's resolution, as ``encode`` would send it."""
        return round_half_away(value, self.frac_digits) / self.scale

    def encode_counts(self, counts: int) -> bytes:
        if abs(counts) > self.max_counts:
            raise UsageError(
                f"{counts / self.scale:g} does not fit BCD format {self.name} "
                f"(|value| <= {self.max_value:g})"
            )
        digits = str(abs(counts)).rjust(self.int_digits + self.frac_digits, "0")
        # A negative zero is sent as positive: the sign nibble is only ever 1 for < 0.
        nibbles = [1 if counts < 0 else 0, *(int(d) for d in digits)]
        return bytes(nibbles[i] << 4 | nibbles[i + 1] for i in range(0, len(nibbles), 2))

    def decode_counts(self, data: bytes) -> int:
        """Decode to an exact integer count of the last digit (sign applied)."""
        if len(data) != self.size:
            raise BadLength(f"BCD {self.name} needs {self.size} bytes, got {len(data)}")
        sign, magnitude = data[0] >> 4, data[0] & 0x0F  # the first digit shares a byte
        if sign > 1:
            raise BadBcd(f"BCD {self.name}: sign nibble {sign:X} in {data.hex(' ')}")
        if magnitude > 9:
            magnitude = _NOT_DECIMAL
        for byte in data[1:]:
            magnitude = magnitude * 100 + _PAIRS[byte]
        if magnitude < 0:
            raise BadBcd(f"BCD {self.name}: non-decimal nibble in {data.hex(' ')}")
        return -magnitude if sign else magnitude

    def decode(self, data: bytes) -> float:
        # Division of an exact integer by a power of ten gives the nearest float to the
        # printed decimal, which is what the document's examples show.
        return self.decode_counts(data) / self.scale


# The six value layouts of the native protocol (section numbers of the native document).
ANGLE = BcdFormat("angle SXXX.YY deg", 3, 2)  # 2.1-2.3, 2.20
ACCEL = BcdFormat("acceleration SX.XXXX g", 1, 4)  # 2.10
RATE = BcdFormat("angular rate SXXX.YY deg/s", 3, 2)  # 2.11
MAG = BcdFormat("magnetic field S.YYYYY gauss", 0, 5)  # 2.23
QUATERNION = BcdFormat("quaternion SX.YYYYYY", 1, 6)  # 2.12
DECLINATION = BcdFormat("declination SXX.Y deg", 2, 1)  # 2.21, 2.22

FORMATS: tuple[BcdFormat, ...] = (ANGLE, ACCEL, RATE, MAG, QUATERNION, DECLINATION)
