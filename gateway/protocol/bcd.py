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
from dataclasses import dataclass

from .errors import BadBcd, BadLength, UsageError


@dataclass(frozen=True, slots=True)
class BcdFormat:
    """One packed-BCD value layout: a sign nibble, then integer and decimal digits."""

    name: str
    int_digits: int
    frac_digits: int

    @property
    def size(self) -> int:
        """Bytes on the wire: the sign nibble and every digit, two nibbles to a byte."""
        return (1 + self.int_digits + self.frac_digits) // 2

    @property
    def scale(self) -> int:
        """Counts of the last digit per unit: 100 for ``SXXX.YY``."""
        return int(10**self.frac_digits)

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
        """Encode ``value`` rounded to this format's resolution.

        Raises ``UsageError`` when the rounded magnitude does not fit (or is not finite).
        """
        if not math.isfinite(value):
            raise UsageError(f"{value} cannot be sent as BCD {self.name}")
        counts = round(value * self.scale)
        return self.encode_counts(counts)

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
        nibbles = [n for byte in data for n in (byte >> 4, byte & 0x0F)]
        sign, digits = nibbles[0], nibbles[1:]
        if sign > 1:
            raise BadBcd(f"BCD {self.name}: sign nibble {sign:X} in {data.hex(' ')}")
        if any(d > 9 for d in digits):
            raise BadBcd(f"BCD {self.name}: non-decimal nibble in {data.hex(' ')}")
        magnitude = int("".join(map(str, digits)))
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
