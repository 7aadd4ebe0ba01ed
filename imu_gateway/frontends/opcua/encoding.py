"""The binary encoding of a sample's values (DataValue), done here for what the gateway
writes; and the MonitoredItemNotification of one, made for less.

asyncua encodes every structure with one generic serializer per dataclass: for each
field a ``getattr``, a closure, and a loop over the optional fields to work out the
encoding mask.  A DataValue took 2.7 µs; a sample of an AH is 19 of them for a client
at sampling interval 0, and with the notifications' creation (below) this was about a
quarter of what OPC UA cost a sample (docs/benchmarks.md, "OPC UA's own encoding").
Here a DataValue of the gateway's takes 0.8 µs: a ``struct`` pack per part, and the
timestamps, which every value of one sample shares, converted once.

The fast path takes exactly what the gateway writes: a scalar Variant of a numeric,
Boolean or String type (or none), a StatusCode, either timestamp, no picoseconds.
Anything else (an array, a LocalizedText, picoseconds, a value that does not fit its
type) goes to asyncua's own serializer, errors included.  The bytes are asyncua's in
every case: ``tests/frontends/opcua/test_opcua_encoding.py`` compares the two over
every type and combination of fields.

``notification`` makes a MonitoredItemNotification with its value given: asyncua's
``MonitoredItemNotification()`` builds a default DataValue (with its Variant and
StatusCode) only to throw it away, 3.1 µs against 0.2.
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Callable
from dataclasses import fields
from datetime import datetime
from typing import Any

from asyncua import ua
from asyncua.ua import ua_binary

_Serializer = Callable[[Any], bytes]

#: Variant types packed here: (encoding byte, their ``struct`` format as asyncua's)
_SCALARS: dict[Any, tuple[bytes, _Serializer]] = {
    vtype: (bytes([vtype.value]),
            struct.Struct(getattr(ua_binary.Primitives, vtype.name).format).pack)
    for vtype in (ua.VariantType.Boolean, ua.VariantType.SByte, ua.VariantType.Byte,
                  ua.VariantType.Int16, ua.VariantType.UInt16, ua.VariantType.Int32,
                  ua.VariantType.UInt32, ua.VariantType.Int64, ua.VariantType.UInt64,
                  ua.VariantType.Float, ua.VariantType.Double)
}
_STRING = ua.VariantType.String
_STRING_TAG = bytes([_STRING.value])
_UINT32 = struct.Struct("<I").pack
_INT64 = struct.Struct("<q").pack


class _Encoder:
    """The DataValue serializer, with asyncua's (``slow``) for the rest.  The last
    timestamp converted is kept (a sample's values share it)."""

    def __init__(self, slow: _Serializer) -> None:
        self.slow = slow
        self._last: tuple[datetime | None, bytes] = (None, b"")

    def _time(self, when: datetime) -> bytes:
        last, packed = self._last
        if when is not last:
            packed = _INT64(ua.datetime_to_win_epoch(when))
            self._last = (when, packed)
        return packed

    @staticmethod
    def _variant(variant: Any) -> bytes | None:
        """The Variant's bytes, or None: not a case of the fast path."""
        if variant.is_array or variant.Dimensions is not None:
            return None
        value = variant.Value
        vtype = variant.VariantType
        scalar = _SCALARS.get(vtype)
        if scalar is not None and not isinstance(value, list | tuple):
            tag, pack = scalar
            try:
                return tag + pack(value)
            except (struct.error, TypeError, OverflowError):
                return None  # (asyncua's error says which value did not fit)
        if vtype is _STRING and (value is None or type(value) is str):
            text: bytes = ua_binary.Primitives.String.pack(value)
            return _STRING_TAG + text
        return None

    def data_value(self, dv: Any) -> bytes:
        if dv.SourcePicoseconds is not None or dv.ServerPicoseconds is not None:
            return self.slow(dv)
        mask, parts = 0, [b""]
        if dv.Value is not None:
            variant = self._variant(dv.Value)
            if variant is None:
                return self.slow(dv)
            mask, parts = 1, [b"", variant]
        if dv.StatusCode is not None:
            mask |= 2
            parts.append(_UINT32(dv.StatusCode.value))
        if dv.SourceTimestamp is not None:
            mask |= 4
            parts.append(self._time(dv.SourceTimestamp))
        if dv.ServerTimestamp is not None:
            mask |= 8
            parts.append(self._time(dv.ServerTimestamp))
        parts[0] = bytes([mask])
        return b"".join(parts)


def notification(client_handle: int, value: Any) -> Any:
    """A MonitoredItemNotification of ``value`` (no default DataValue built first)."""
    return ua.MonitoredItemNotification(client_handle, value)


_installed: _Encoder | None = None


def install() -> None:
    """Make asyncua encode DataValues here, once per process.  asyncua encodes a
    structure inside another (a notification's value, a read's result) through
    ``struct_to_binary``, which looks the serializer up by the value's class each time:
    that lookup is where this one goes in."""
    global _installed
    if _installed is not None:
        return
    original = ua_binary.create_dataclass_serializer
    encoder = _Encoder(original(ua.DataValue))

    @functools.cache  # (asyncua looks it up for each structure it encodes)
    def create_dataclass_serializer(dataclazz: type) -> _Serializer:
        if issubclass(dataclazz, ua.DataValue) and fields(dataclazz) == fields(ua.DataValue):
            return encoder.data_value  # (and the gateway's ``Sample``: no field of its own)
        serializer: _Serializer = original(dataclazz)
        return serializer

    ua_binary.create_dataclass_serializer = create_dataclass_serializer
    # (serializers made before and cached would keep asyncua's)
    for cached in (ua_binary.create_type_serializer, ua_binary.create_list_serializer):
        cached.cache_clear()
    _installed = encoder


def reference() -> _Serializer:
    """asyncua's own DataValue serializer (for the tests and the bench to compare)."""
    install()
    assert _installed is not None
    return _installed.slow
