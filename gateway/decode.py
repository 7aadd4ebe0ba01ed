"""``imu-gateway decode``: captured frames to JSON, for a field engineer with a capture.

A data answer becomes the value groups of the reading JSON (docs/mqtt.md); any other
frame becomes ``{"command": …, "direction": …, "address": …, "fields": {…}}``.
A Modbus read answer is read in the light of the read request before it in the same
call, or of ``--start``.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

from .model import CAPABILITIES, Protocol, Series
from .normalise import FIELD_NAMES, group_values
from .protocol import modbus_rtu as rtu
from .protocol import native
from .protocol.errors import FrameError, ProtocolError


class BadInput(ProtocolError):
    """The argument is not a frame at all (not hex, empty)."""


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


def _native(raw: bytes, series: Series | None) -> dict[str, Any]:
    message = native.decode(raw, series)
    direction = {
        native.Direction.REQUEST: "request",
        native.Direction.ANSWER: "answer",
        native.Direction.ECHO: "request/echo",
    }[message.shape.direction]
    header = {"command": message.name, "direction": direction, "address": message.address,
              "section": message.shape.section}
    values = dict(message.values)
    if message.shape.direction is native.Direction.ANSWER:
        return _groups_or_fields(values, series, header, values)
    return {**header, "fields": values}


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


def _guess_protocol(raw: bytes) -> Protocol:
    if raw[0] == native.SYNC:
        try:
            native.parse_frame(raw)
            return Protocol.NATIVE
        except FrameError:
            try:
                rtu.decode_frame(raw)
                return Protocol.MODBUS
            except FrameError:
                return Protocol.NATIVE  # report the native reason: 77 is its sync byte
    return Protocol.MODBUS


def decode_all(
    frames: Iterable[str],
    protocol: Protocol | None = None,
    series: Series | None = None,
    start: int | None = None,
) -> Iterator[Decoded]:
    """Each frame decoded, or the reason it is not a frame; never raises for bad input."""
    pending_start = start
    for text in frames:
        try:
            raw = parse_hex(text)
            proto = protocol or _guess_protocol(raw)
            if proto is Protocol.NATIVE:
                result = _native(raw, series)
            else:
                result, request_start = _modbus(raw, series, pending_start)
                pending_start = request_start if request_start is not None else start
            yield Decoded(text, result, None)
        except ProtocolError as exc:
            yield Decoded(text, None, f"{type(exc).__name__}: {exc}")


def to_json_line(result: dict[str, Any]) -> str:
    return json.dumps(result, separators=(", ", ": "))
