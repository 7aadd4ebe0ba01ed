"""``imu-gateway decode``: captured frames to JSON, for a field engineer with a capture.

A data answer becomes the value groups of the reading JSON (docs/mqtt.md); any other
frame becomes ``{"command": …, "direction": …, "address": …, "fields": {…}}``.
A Modbus read answer is read in the light of the read request before it in the same
call, or of ``--start``.  A native frame that is one command as a request and another
as an answer (2.16) is shown both ways: ``fields`` as the request, ``answer_fields``
as the answer.

What is not one whole frame gets the likeliest reason, not merely the first check that
failed: a native frame with bytes before or after it is named as such (rather than
guessed to be Modbus with a bad CRC), and a Modbus frame cut short says how many of
its bytes are there.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from ..model import CAPABILITIES, Series, WireProtocol
from ..normalise import FIELD_NAMES, group_values
from ..protocol import modbus_rtu as rtu
from ..protocol import native
from ..protocol.errors import FrameError, ProtocolError


class BadInput(ProtocolError):
    """The argument is not a frame at all (not hex, empty)."""


class FrameInside(FrameError):
    """A whole frame lies within the bytes given, with other bytes around it."""


@dataclass(frozen=True, slots=True)
class Decoded:
    text: str  # the frame as given, for messages
    result: dict[str, Any] | None
    error: str | None


def parse_hex(text: str) -> bytes:
    cleaned = "".join(text.replace("0x", "").replace(",", " ").split())
    if not cleaned:
        raise BadInput("empty frame")
    try:
        return bytes.fromhex(cleaned)
    except ValueError:
        raise BadInput(f"not a hex string: {text!r}") from None


def _groups_or_fields(
    values: dict[str, Any], series: Series | None, header: dict[str, Any],
    fields: dict[str, Any],
) -> dict[str, Any]:
    """The reading JSON's value groups when ``values`` are all measurements (and the
    series measures some of them), else the command form with ``fields``."""
    if values and all(name in FIELD_NAMES for name in values):
        groups = group_values(values)
        if series is not None:
            keep = {g.value for g in CAPABILITIES[series].groups}
            groups = {name: v for name, v in groups.items() if name in keep}
        if groups:
            return dict(groups)
    return {**header, "fields": fields}


_DIRECTIONS = {
    native.Direction.REQUEST: "request",
    native.Direction.ANSWER: "answer",
    native.Direction.ECHO: "request/echo",
}


def _native(raw: bytes, series: Series | None) -> dict[str, Any]:
    frame = native.parse_frame(raw)
    if (frame.command, len(frame.data) + 4) in native.TWO_WAY:
        return _native_two_way(frame, series)
    message = native.interpret(frame, series)
    header = {"command": message.name, "direction": _DIRECTIONS[message.shape.direction],
              "address": message.address, "section": message.shape.section}
    values = dict(message.values)
    if message.shape.direction is native.Direction.ANSWER:
        # A native answer carries what its shape says and nothing left at zero: its
        # groups are shown whatever the series (an IMU's 2.3 answer has angles).
        return _groups_or_fields(values, None, header, values)
    return {**header, "fields": values}


def _native_two_way(frame: native.NativeFrame, series: Series | None) -> dict[str, Any]:
    """A frame whose bytes are a request one way and an answer the other (2.16's
    ``77 05 .. 56 XX``: output type XX asked, or status XX answered): both readings."""
    request = native.interpret(frame, series, native.Direction.REQUEST)
    answer = native.interpret(frame, series, native.Direction.ANSWER)
    return {"command": request.name, "direction": "request or answer",
            "address": request.address, "section": request.shape.section,
            "fields": dict(request.values), "answer_fields": dict(answer.values)}


def _modbus(
    raw: bytes, series: Series | None, start: int | None
) -> tuple[dict[str, Any], int | None]:
    """The frame's JSON, and the start register a following answer should be read with."""
    message = rtu.decode_frame(raw)
    described = rtu.describe(message, start if isinstance(message, rtu.ReadResponse) else None)
    header = {"command": described.pop("frame"), "address": described.pop("unit")}
    if isinstance(message, rtu.ReadRequest):
        return {**header, "fields": described}, message.address
    return _groups_or_fields(described.get("values", {}), series, header, described), None


def _guess_protocol(raw: bytes) -> WireProtocol:
    if raw[0] == native.SYNC:
        try:
            native.parse_frame(raw)
            return WireProtocol.NATIVE
        except FrameError:
            try:
                rtu.decode_frame(raw)
                return WireProtocol.MODBUS
            except FrameError:
                return WireProtocol.NATIVE  # report the native reason: 77 is its sync byte
    return WireProtocol.MODBUS


def _native_inside(raw: bytes) -> str | None:
    """Where ``raw`` is not one native frame but holds one whole (its LEN, checksum
    and shape right) with bytes before or after it: what it most likely is, in words."""
    for start in (i for i, byte in enumerate(raw) if byte == native.SYNC):
        if start + 1 >= len(raw):
            break
        end = start + raw[start + 1] + 1
        if end > len(raw) or (start == 0 and end == len(raw)):
            continue
        try:
            message = native.decode(raw[start:end])
        except FrameError:
            continue
        where = [f"after {_bytes(start, 'garbage ')}"] if start else []
        if end < len(raw):
            where.append(f"followed by {_bytes(len(raw) - end, 'more ')}")
        return (f"native frame {' and '.join(where)}: {raw[start:end].hex(' ').upper()} "
                f"({message.name} {_DIRECTIONS[message.shape.direction]}, "
                f"{message.shape.section}); decode it alone")
    return None


def _modbus_inside(raw: bytes) -> str | None:
    """The same for a whole Modbus frame at the end of ``raw`` behind garbage (an RTU
    frame has no sync byte, so only a frame that runs to the end is looked for)."""
    for start in range(1, len(raw) - 3):
        try:
            message = rtu.decode_frame(raw[start:])
        except FrameError:
            continue
        kind = rtu.describe(message)["frame"]
        return (f"Modbus frame after {_bytes(start, 'garbage ')}: "
                f"{raw[start:].hex(' ').upper()} ({kind}); decode it alone")
    return None


def _bytes(count: int, kind: str = "") -> str:
    return f"{count} {kind}byte{'s' if count != 1 else ''}"


def _decode_one(raw: bytes, protocol: WireProtocol | None, series: Series | None,
                start: int | None) -> tuple[dict[str, Any], int | None]:
    """One frame's JSON and the start register a following answer is read with; a
    frame that is not one whole frame raises with its likeliest reason."""
    proto = protocol or _guess_protocol(raw)
    try:
        if proto is WireProtocol.NATIVE:
            return _native(raw, series), None
        return _modbus(raw, series, start)
    except FrameError:
        inside = None
        if protocol is not WireProtocol.MODBUS:
            inside = _native_inside(raw)
        if inside is None and protocol is not WireProtocol.NATIVE:
            inside = _modbus_inside(raw)
        if inside is not None:
            raise FrameInside(inside) from None
        raise


def decode_all(
    frames: Iterable[str],
    protocol: WireProtocol | None = None,
    series: Series | None = None,
    start: int | None = None,
) -> Iterator[Decoded]:
    """Each frame decoded, or the reason it is not a frame; never raises for bad input."""
    pending_start = start
    for text in frames:
        try:
            raw = parse_hex(text)
            result, request_start = _decode_one(raw, protocol, series, pending_start)
            pending_start = request_start if request_start is not None else start
            yield Decoded(text, result, None)
        except ProtocolError as exc:
            yield Decoded(text, None, f"{type(exc).__name__}: {exc}")


def to_json_line(result: dict[str, Any]) -> str:
    return json.dumps(result, separators=(", ", ": "))
