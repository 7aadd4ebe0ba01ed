"""Packed BCD with a sign nibble (``imu_gateway.protocol.bcd``).

Every value example of the native document, per format, both ways; the refusals
(bad nibbles, values that do not fit, wrong lengths); and Hypothesis round trips over
each format's whole range.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from imu_gateway.protocol import bcd
from imu_gateway.protocol.errors import BadBcd, BadLength, FrameError, UsageError

# (format, bytes as printed, value as printed), from the native document's sections.
EXAMPLES = [
    (bcd.ANGLE, "10 34 63", -34.63),  # 2.1
    (bcd.ANGLE, "01 23 57", 123.57),  # 2.2
    (bcd.ANGLE, "00 02 01", 2.01),  # 2.3
    (bcd.ANGLE, "10 00 51", -0.51),  # 2.3
    (bcd.ANGLE, "00 00 00", 0.0),  # 2.3
    (bcd.ANGLE, "01 00 00", 100.0),  # 2.20
    (bcd.ANGLE, "10 00 60", -0.6),  # 2.14
    (bcd.ANGLE, "02 51 87", 251.87),  # 2.15
    (bcd.ACCEL, "00 01 07", 0.0107),  # 2.10
    (bcd.ACCEL, "00 94 21", 0.9421),  # 2.10
    (bcd.ACCEL, "10 06 30", -0.0630),  # 2.10
    (bcd.ACCEL, "01 01 54", 1.0154),  # 2.14
    (bcd.ACCEL, "10 18 07", -0.1807),  # 2.15
    (bcd.RATE, "10 93 76", -93.76),  # 2.11
    (bcd.RATE, "14 98 87", -498.87),  # 2.11
    (bcd.RATE, "00 14 03", 14.03),  # 2.11
    (bcd.RATE, "12 98 87", -298.87),  # 2.13
    (bcd.RATE, "01 24 13", 124.13),  # 2.15
    (bcd.MAG, "11 55 25", -0.15525),  # 2.23
    (bcd.MAG, "00 34 52", 0.03452),  # 2.23
    (bcd.MAG, "13 46 16", -0.34616),  # 2.23
    (bcd.MAG, "01 59 62", 0.15962),  # 2.15
    (bcd.MAG, "14 14 58", -0.41458),  # 2.15
    (bcd.QUATERNION, "00 99 99 96", 0.999996),  # 2.12
    (bcd.QUATERNION, "00 00 02 90", 0.000290),  # 2.12
    (bcd.QUATERNION, "10 00 26 73", -0.002673),  # 2.12
    (bcd.QUATERNION, "10 00 00 01", -0.000001),  # 2.12
    (bcd.QUATERNION, "10 87 06 35", -0.870635),  # 2.14
    (bcd.QUATERNION, "00 93 99 14", 0.939914),  # 2.15
    (bcd.DECLINATION, "02 08", 20.8),  # 2.21, 2.22
]
FORMAT_IDS = [f.name for f in bcd.FORMATS]


def _example_id(example: tuple[bcd.BcdFormat, str, float]) -> str:
    return f"{example[0].name.split()[0]}:{example[1]}"


def _nibbles_to_bytes(nibbles: list[int]) -> bytes:
    return bytes(nibbles[i] << 4 | nibbles[i + 1] for i in range(0, len(nibbles), 2))


@pytest.mark.parametrize("example", EXAMPLES, ids=_example_id)
def test_document_example_decodes(example: tuple[bcd.BcdFormat, str, float]) -> None:
    fmt, hex_, value = example
    # counts / scale is a correctly rounded division, so it *is* the printed decimal.
    assert fmt.decode(bytes.fromhex(hex_)) == value
    assert fmt.decode_counts(bytes.fromhex(hex_)) == round(value * fmt.scale)


@pytest.mark.parametrize("example", EXAMPLES, ids=_example_id)
def test_document_example_encodes(example: tuple[bcd.BcdFormat, str, float]) -> None:
    fmt, hex_, value = example
    assert fmt.encode(value) == bytes.fromhex(hex_)


@pytest.mark.parametrize(
    ("fmt", "size", "scale", "max_value"),
    [
        (bcd.ANGLE, 3, 100, 999.99),
        (bcd.ACCEL, 3, 10_000, 9.9999),
        (bcd.RATE, 3, 100, 999.99),
        (bcd.MAG, 3, 100_000, 0.99999),
        (bcd.QUATERNION, 4, 1_000_000, 9.999999),
        (bcd.DECLINATION, 2, 10, 99.9),
    ],
    ids=FORMAT_IDS,
)
def test_format_geometry(fmt: bcd.BcdFormat, size: int, scale: int, max_value: float) -> None:
    assert (fmt.size, fmt.scale, fmt.max_value) == (size, scale, max_value)
    assert fmt.resolution == 1 / scale


@pytest.mark.parametrize("fmt", bcd.FORMATS, ids=FORMAT_IDS)
@pytest.mark.parametrize("sign", range(2, 16), ids=lambda s: f"sign{s:X}")
def test_sign_nibble_above_one_is_bad(fmt: bcd.BcdFormat, sign: int) -> None:
    data = _nibbles_to_bytes([sign] + [0] * (2 * fmt.size - 1))
    with pytest.raises(BadBcd):
        fmt.decode(data)


@pytest.mark.parametrize("fmt", bcd.FORMATS, ids=FORMAT_IDS)
@pytest.mark.parametrize("digit", range(0xA, 0x10), ids=lambda d: f"digit{d:X}")
def test_digit_nibble_above_nine_is_bad(fmt: bcd.BcdFormat, digit: int) -> None:
    for position in range(1, 2 * fmt.size):
        for sign in (0, 1):
            nibbles = [sign] + [5] * (2 * fmt.size - 1)
            nibbles[position] = digit
            with pytest.raises(BadBcd):
                fmt.decode(_nibbles_to_bytes(nibbles))


def test_bad_bcd_is_a_frame_error() -> None:
    with pytest.raises(FrameError):
        bcd.ANGLE.decode(bytes.fromhex("0A 00 00"))


@pytest.mark.parametrize("fmt", bcd.FORMATS, ids=FORMAT_IDS)
def test_out_of_range_encode_is_usage_error(fmt: bcd.BcdFormat) -> None:
    too_big = (fmt.max_counts + 1) / fmt.scale
    for value in (too_big, -too_big, 1e9, -1e9):
        with pytest.raises(UsageError):
            fmt.encode(value)
        with pytest.raises(ValueError):  # a UsageError is also a ValueError
            fmt.encode(value)
    for counts in (fmt.max_counts + 1, -fmt.max_counts - 1):
        with pytest.raises(UsageError):
            fmt.encode_counts(counts)


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_non_finite_encode_is_usage_error(value: float) -> None:
    """An infinite or NaN value does not fit any format either (JSON commands may carry
    ``Infinity``/``NaN``): the same UsageError, not an OverflowError/ValueError from
    round()."""
    for fmt in bcd.FORMATS:
        with pytest.raises(UsageError):
            fmt.encode(value)


@pytest.mark.parametrize("fmt", bcd.FORMATS, ids=FORMAT_IDS)
def test_range_edges_encode(fmt: bcd.BcdFormat) -> None:
    assert fmt.decode(fmt.encode(fmt.max_value)) == fmt.max_value
    assert fmt.decode(fmt.encode(-fmt.max_value)) == -fmt.max_value


@pytest.mark.parametrize("fmt", bcd.FORMATS, ids=FORMAT_IDS)
def test_wrong_length_is_bad_length(fmt: bcd.BcdFormat) -> None:
    for size in (0, fmt.size - 1, fmt.size + 1):
        with pytest.raises(BadLength):
            fmt.decode(bytes(size))
        with pytest.raises(BadLength):
            fmt.decode_counts(bytes(size))


@pytest.mark.parametrize("fmt", bcd.FORMATS, ids=FORMAT_IDS)
def test_negative_zero_has_sign_nibble_zero(fmt: bcd.BcdFormat) -> None:
    assert fmt.encode(-0.0) == bytes(fmt.size)
    # less than half a last digit below zero rounds to zero, and zero is positive
    assert fmt.encode(-0.4 * fmt.resolution) == bytes(fmt.size)
    assert fmt.encode_counts(-0) == bytes(fmt.size)


@st.composite
def _format_and_counts(draw: st.DrawFn) -> tuple[bcd.BcdFormat, int]:
    fmt = draw(st.sampled_from(bcd.FORMATS))
    return fmt, draw(st.integers(-fmt.max_counts, fmt.max_counts))


@settings(max_examples=300)
@given(_format_and_counts())
def test_counts_round_trip(case: tuple[bcd.BcdFormat, int]) -> None:
    fmt, counts = case
    data = fmt.encode_counts(counts)
    assert len(data) == fmt.size
    assert data[0] >> 4 == (1 if counts < 0 else 0)
    assert fmt.decode_counts(data) == counts


@settings(max_examples=300)
@given(_format_and_counts())
def test_value_round_trip(case: tuple[bcd.BcdFormat, int]) -> None:
    fmt, counts = case
    value = counts / fmt.scale
    data = fmt.encode(value)
    assert data == fmt.encode_counts(counts)
    assert fmt.decode(data) == value


def test_each_value_group_s_span_is_its_native_format_s_largest_value() -> None:
    """OPC UA's EURange comes from ``ValueGroup.span``: it must be what the format
    can carry (the model may not import the protocol layer, so the two are held
    together here)."""
    from imu_gateway.model import VALUE_GROUPS, Group
    from imu_gateway.protocol import bcd

    formats = {Group.ANGLES: bcd.ANGLE, Group.ACCEL: bcd.ACCEL, Group.GYRO: bcd.RATE,
               Group.MAG: bcd.MAG, Group.QUATERNION: bcd.QUATERNION}
    for group, fmt in formats.items():
        largest = 10**fmt.int_digits - 10**-fmt.frac_digits
        assert VALUE_GROUPS[group].span == pytest.approx(largest, abs=1e-12), group
        assert VALUE_GROUPS[group].digits == fmt.frac_digits
