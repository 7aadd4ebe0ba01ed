"""``imu-gateway decode``'s reading of frames (``imu_gateway.tools.decode``), called in-process:
what a frame that is not one whole frame most likely is, the 2.16 frame read both
ways, the native reads any series answers, and Modbus frames of any address.

``tests/tools/test_cli.py`` runs the command itself; these check the wording and the cases.
"""

from __future__ import annotations

from typing import Any

import pytest

from imu_gateway.model import Series, WireProtocol
from imu_gateway.protocol import modbus_rtu as rtu
from imu_gateway.tools.decode import decode_all

PITCH = "77 07 00 81 10 34 63 2F"  # native 2.1's answer: -34.63


def one(frame: str, protocol: WireProtocol | None = None, series: Series | None = None,
        start: int | None = None) -> tuple[dict[str, Any] | None, str | None]:
    (decoded,) = decode_all([frame], protocol, series, start)
    return decoded.result, decoded.error


@pytest.mark.parametrize(("frame", "reason"), [
    ("12 34 56 " + PITCH,
     f"FrameInside: native frame after 3 garbage bytes: {PITCH} (read_pitch answer, 2.1)"),
    ("00 " + PITCH, "native frame after 1 garbage byte: "),
    (PITCH + " 00 11", f"native frame followed by 2 more bytes: {PITCH}"),
    ("AB " + PITCH + " CD", "native frame after 1 garbage byte and followed by 1 more byte"),
])
def test_native_frame_among_other_bytes_is_named_as_such(frame: str, reason: str) -> None:
    """Before, a native frame behind garbage was guessed to be Modbus and reported as a
    CRC error."""
    result, error = one(frame)
    assert result is None and error is not None
    assert reason in error, error
    assert "CRC" not in error


def test_garbage_before_a_native_frame_is_named_when_the_protocol_is_given_too() -> None:
    assert "native frame after 3 garbage bytes" in str(one("12 34 56 " + PITCH,
                                                           WireProtocol.NATIVE)[1])
    # told it is Modbus, the Modbus reason stands
    assert "FrameInside" not in str(one("12 34 56 " + PITCH, WireProtocol.MODBUS)[1])


@pytest.mark.parametrize(("frame", "reason"), [
    ("01 03 04 50 A7 4C EE", "BadLength: truncated: 7 of 9 bytes (an FC03 frame)"),
    ("01 06 00 0A 00", "BadLength: truncated: 5 of 8 bytes (an FC06 frame)"),
    ("01 03 02 4E 7D 4D C6", "BadChecksum"),  # whole, its CRC wrong
])
def test_modbus_frame_cut_short_says_so(frame: str, reason: str) -> None:
    assert reason in str(one(frame)[1])


def test_modbus_frame_behind_garbage_is_named() -> None:
    error = str(one("AA 01 03 02 4E 7D 4D C5")[1])
    assert "Modbus frame after 1 garbage byte: 01 03 02 4E 7D 4D C5 (read_response)" in error


@pytest.mark.parametrize("unit", [0, 248, 254, 255])
def test_any_modbus_frame_with_a_valid_crc_is_decoded(unit: int) -> None:
    write = rtu.encode(rtu.WriteRegister(unit, 0x0A, 1)).hex(" ")
    result, error = one(write)
    assert error is None and result is not None
    assert result == {"command": "write", "address": unit,
                      "fields": {"address": 0x0A, "raw": 1, "register": "set_zero_type",
                                 "value": "relative"}}
    answer = rtu.encode(rtu.ReadResponse(unit, (20093,))).hex(" ")
    assert one(answer, start=1) == ({"angles": {"pitch": 0.93}}, None)


def test_output_type_frame_is_shown_as_request_and_as_answer() -> None:
    """2.16: the same bytes ask for a type and answer with a status."""
    assert one("77 05 00 56 00 5B") == ({
        "command": "set_output_type", "direction": "request or answer", "address": 0,
        "section": "2.16", "fields": {"output_type": 0},
        "answer_fields": {"result": "success"}}, None)
    result, _ = one("77 05 00 56 FF 5A")
    assert result is not None and result["answer_fields"] == {"result": "failure"}


@pytest.mark.parametrize("series", list(Series), ids=lambda s: s.name)
def test_reads_that_name_no_series_decode_for_any_series(series: Series) -> None:
    assert one(PITCH, series=series) == ({"angles": {"pitch": -34.63}}, None)
    angles = "77 0D 00 84 00 02 01 10 00 51 00 00 00 F5"
    assert one(angles, series=series) == (
        {"angles": {"pitch": 2.01, "roll": -0.51, "yaw": 0.0}}, None)


def test_unknown_baud_code_request_decodes() -> None:
    assert one("77 05 00 0B 09 19") == ({
        "command": "set_baudrate", "direction": "request", "address": 0, "section": "2.4",
        "fields": {"baudrate": 9}}, None)
