"""The gateway's DataValue encoding (``frontends/opcua/encoding.py``) gives asyncua's
bytes for every DataValue, and asyncua's errors for those it cannot encode; a
notification message of them decodes back to what was sent."""

from __future__ import annotations

import itertools
import math
from datetime import UTC, datetime, timedelta
from typing import Any

import pytest
from asyncua import ua
from asyncua.common.utils import Buffer
from asyncua.ua import ua_binary
from asyncua.ua.uaerrors import UaError

from imu_gateway.frontends.opcua import encoding
from imu_gateway.frontends.opcua.server import Sample

V = ua.VariantType
NOW = datetime(2026, 11, 27, 3, 4, 5, 678901, tzinfo=UTC)

#: Each scalar type with its limits and a few ordinary values.
SCALARS: dict[Any, list[Any]] = {
    V.Boolean: [True, False],
    V.SByte: [-128, 0, 127], V.Byte: [0, 255],
    V.Int16: [-32768, 32767], V.UInt16: [0, 65535],
    V.Int32: [-2**31, 0, 2**31 - 1], V.UInt32: [0, 2**32 - 1],
    V.Int64: [-2**63, 2**63 - 1], V.UInt64: [0, 2**64 - 1],
    V.Float: [0.0, -1.5, 3.4028234e38, math.inf, math.nan, 1.2345678],
    V.Double: [0.0, -0.0, 1.2345, -273.15, 1e308, -math.inf, math.nan],
    V.String: ["", "online", "Neigung 3°", None],
}
#: Variants the fast path leaves to asyncua.
OTHERS = [
    ua.Variant(None, V.Null),
    ua.Variant([1.0, 2.0], V.Double),
    ua.Variant([[1, 2], [3, 4]], V.Int32, Dimensions=[2, 2]),
    ua.Variant(ua.LocalizedText("a", "en"), V.LocalizedText),
    ua.Variant(NOW, V.DateTime),
    ua.Variant(b"\x01\x02", V.ByteString),
]
STATUSES = [None, ua.StatusCode(), ua.StatusCode(ua.StatusCodes.BadNoCommunication),
            ua.StatusCode(ua.StatusCodes.UncertainLastUsableValue)]
TIMES = [None, NOW, NOW.replace(tzinfo=None), datetime(1500, 1, 1, tzinfo=UTC),
         datetime(9999, 12, 31, 23, 59, 59, tzinfo=UTC), NOW + timedelta(microseconds=1)]


def variants() -> list[Any]:
    out = [ua.Variant(v, t) for t, values in SCALARS.items() for v in values]
    return out + OTHERS


def data_values() -> list[Any]:
    out = []
    for variant, status, (source, server) in itertools.product(
            variants(), STATUSES, [(NOW, NOW), (None, None), (TIMES[2], None), (None, TIMES[3]),
                                   (TIMES[4], TIMES[5])]):
        out.append(ua.DataValue(variant, status, SourceTimestamp=source, ServerTimestamp=server))
    out += [ua.DataValue(ua.Variant(1.0, V.Double), SourceTimestamp=NOW, SourcePicoseconds=5),
            ua.DataValue(ua.Variant(1.0, V.Double), ServerTimestamp=NOW, ServerPicoseconds=9),
            ua.DataValue(None, ua.StatusCode(ua.StatusCodes.BadNodeIdUnknown), NOW, NOW),
            Sample(ua.Variant(2.5, V.Double), ua.StatusCode(), NOW, NOW)]
    return out


def test_every_data_value_encodes_to_asyncuas_bytes() -> None:
    encoding.install()
    asyncua = encoding.reference()
    values = data_values()
    assert len(values) > 300
    for dv in values:
        assert ua_binary.struct_to_binary(dv) == asyncua(dv), dv


def test_a_value_that_does_not_fit_its_type_is_asyncuas_error() -> None:
    encoding.install()
    for variant in [ua.Variant(256, V.Byte), ua.Variant(2**63, V.Int64), ua.Variant("x", V.Double),
                    ua.Variant(1e39, V.Float)]:
        with pytest.raises(UaError, match="Cannot pack VariantType"):
            ua_binary.struct_to_binary(ua.DataValue(variant))


def test_the_timestamp_kept_serves_only_the_same_time() -> None:
    """The last timestamp converted is kept: the times that follow, the same, an equal
    copy, another and the first again, each get their own bytes."""
    encoding.install()
    asyncua = encoding.reference()
    later = NOW + timedelta(seconds=1)
    for when in (NOW, NOW.replace(), later, NOW):
        dv = ua.DataValue(ua.Variant(1.0, V.Double), SourceTimestamp=when, ServerTimestamp=later)
        assert ua_binary.struct_to_binary(dv) == asyncua(dv)


def test_a_notification_message_decodes_back_to_its_values() -> None:
    """Encoded through asyncua's own structures (the notification, its list, the
    message, the extension object), decoded by asyncua's decoder."""
    encoding.install()
    values = [dv for dv in data_values() if dv.SourcePicoseconds is None
              and dv.ServerPicoseconds is None and not _has_nan(dv)][:120]
    items = [encoding.notification(handle, dv) for handle, dv in enumerate(values)]
    message = ua.NotificationMessage(SequenceNumber=7, PublishTime=NOW, NotificationData=[
        ua.DataChangeNotification(MonitoredItems=items)])
    decoded = ua_binary.struct_from_binary(ua.NotificationMessage,
                                           Buffer(ua_binary.struct_to_binary(message)))
    got = decoded.NotificationData[0].MonitoredItems
    assert [item.ClientHandle for item in got] == list(range(len(values)))
    for item, sent in zip(got, values, strict=True):
        assert item.Value.Value.Value == sent.Value.Value
        assert item.Value.StatusCode == sent.StatusCode or (
            sent.StatusCode is None and item.Value.StatusCode == ua.StatusCode())


def _has_nan(dv: Any) -> bool:
    value = dv.Value.Value if dv.Value is not None else None
    return isinstance(value, float) and math.isnan(value)


def test_a_notification_is_made_with_its_value() -> None:
    dv = ua.DataValue(ua.Variant(1.0, V.Double))
    item = encoding.notification(42, dv)
    assert isinstance(item, ua.MonitoredItemNotification)
    assert (item.ClientHandle, item.Value) == (42, dv)
