"""OPC UA HistoryRead (Part 11) over the gateway's history (``imu_gateway.history``):
raw values and Part 13's Minimum, Maximum, Average and Interpolative aggregates.

asyncua's own ``HistoryManager`` serves raw reads from a storage it fills itself (a
second copy of every value) and answers BadNotImplemented to processed reads; here
``GatewayHistory`` replaces it, reading the one history the gateway keeps for every
front end.  The arithmetic is plain functions of kept seconds and times (epoch
seconds), so it is tested without a server; ``HISTORY_DOC`` is its part of
docs/opcua.md.
"""

from __future__ import annotations

import bisect
import enum
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.server.history import HistoryManager
from asyncua.server.internal_server import InternalServer

from ...history import KEEP_S, History, Second

#: Processed values per node in one response; the rest comes on a continuation point
#: (a range of days at 1 s would otherwise be one answer of millions of BadNoData).
MAX_INTERVALS = 1000
# StatusCode info bits (Part 4 7.39, Part 11 6.3): InfoType DataValue, then the
# historian bits.
_DATA_VALUE = 0x400
_CALCULATED, _INTERPOLATED, _PARTIAL = 0x1, 0x2, 0x4
_RAW_POINT = b"igr1"  # continuation points: a tag, then where the next page starts
_PROCESSED_POINT = b"igp1"


class Aggregate(enum.Enum):
    MINIMUM = ua.ObjectIds.AggregateFunction_Minimum
    MAXIMUM = ua.ObjectIds.AggregateFunction_Maximum
    AVERAGE = ua.ObjectIds.AggregateFunction_Average
    INTERPOLATIVE = ua.ObjectIds.AggregateFunction_Interpolative


@dataclass(frozen=True, slots=True)
class Sample:
    """A value of raw history at wire time ``at`` (epoch seconds); ``value`` None: a
    bound asked for that the history does not hold (BadBoundNotFound)."""

    at: float
    value: float | None


@dataclass(frozen=True, slots=True)
class Interval:
    """A processed value: ``value`` None is BadNoData."""

    start: float
    value: float | None
    partial: bool  # shorter than the processing interval (the range's last)


# ------------------------------------------------------------------ raw (Part 11 6.4.3)


def raw_points(seconds: Sequence[Second]) -> list[Sample]:
    """Raw history: each kept second's last value, at its last sample's wire time."""
    return [Sample(s.at, s.last) for s in seconds]


def raw_range(points: Sequence[Sample], first: float, last: float | None, *,
              reverse: bool, bounds: bool, first_bound: bool = True) -> list[Sample]:
    """The points from ``first`` (inclusive) towards ``last`` (exclusive; None: no
    end), oldest first or, ``reverse``, newest first.  With ``bounds`` (ReturnBounds)
    the values just outside: at or before ``first`` (after, in reverse) unless a point
    is at ``first``, and at or after ``last``; a bound not kept is a Sample without a
    value at the bound's time.  A reverse read is a forward one of the negated times."""
    sign = -1.0 if reverse else 1.0
    pts = [Sample(sign * p.at, p.value) for p in (reversed(points) if reverse else points)]
    lo, hi = sign * first, None if last is None else sign * last
    inside = [p for p in pts if p.at >= lo and (hi is None or p.at < hi)]
    out: list[Sample] = []
    if bounds and first_bound and not (inside and inside[0].at == lo):
        before = [p for p in pts if p.at < lo]
        out.append(before[-1] if before else Sample(lo, None))
    out += inside
    if bounds and hi is not None:
        after = [p for p in pts if p.at >= hi]
        out.append(after[0] if after else Sample(hi, None))
    return [Sample(sign * p.at, p.value) for p in out]


# ------------------------------------------------------------------ processed (Part 13)


def interpolate(points: Sequence[Sample], at: float) -> float | None:
    """Part 13 5.4.3.2, Interpolative: the value at ``at``, linear between the kept
    points around it; None where the history holds none on one side."""
    times = [p.at for p in points]
    i = bisect.bisect_right(times, at)
    if i and times[i - 1] == at:
        return points[i - 1].value
    if i == 0 or i == len(points):
        return None
    a, b = points[i - 1], points[i]
    assert a.value is not None and b.value is not None
    return a.value + (b.value - a.value) * (at - a.at) / (b.at - a.at)


def _of(kind: Aggregate, inside: Sequence[Second]) -> float | None:
    if not inside:
        return None
    if kind is Aggregate.MINIMUM:
        return min(s.low for s in inside)
    if kind is Aggregate.MAXIMUM:
        return max(s.high for s in inside)
    # the mean of the raw values: exact, each second keeps their sum and count
    return math.fsum(s.total for s in inside) / sum(s.count for s in inside)


def processed(kind: Aggregate, seconds: Sequence[Second], start: float, end: float,
              step: float, first: int = 0, limit: int = MAX_INTERVALS,
              ) -> tuple[list[Interval], int | None]:
    """Intervals ``[start + k·step, start + (k+1)·step)`` up to ``end`` (step 0: one
    interval), from the ``first``-th, at most ``limit``; with the index of the next one
    when more remain.  A second counts in the interval where it begins."""
    step = step or end - start
    total = math.ceil((end - start) / step) if end > start else 0
    starts = [s.start for s in seconds]
    points = raw_points(seconds) if kind is Aggregate.INTERPOLATIVE else []
    out = []
    for k in range(first, min(total, first + limit)):
        lo, hi = start + k * step, min(start + (k + 1) * step, end)
        if kind is Aggregate.INTERPOLATIVE:
            value = interpolate(points, lo)
        else:
            value = _of(kind, seconds[bisect.bisect_left(starts, lo):
                                      bisect.bisect_left(starts, hi)])
        out.append(Interval(lo, value, hi - lo < step))
    more = first + limit if first + limit < total else None
    return out, more


# ------------------------------------------------------------------ the service


def _epoch(moment: datetime | None) -> float | None:
    """Epoch seconds; None for an unspecified time (DateTime 0, 1601-01-01)."""
    if moment is None:
        return None
    if moment.tzinfo is None:  # (asyncua's own client sends naive UTC)
        moment = moment.replace(tzinfo=UTC)
    if moment <= ua.get_win_epoch():
        return None
    return moment.timestamp()


def _bad(name: str) -> ua.HistoryReadResult:
    return ua.HistoryReadResult(StatusCode=ua.StatusCode(getattr(ua.StatusCodes, name)))


def _pack(tag: bytes, value: float) -> bytes:
    return tag + struct.pack("<d", value)


def _unpack(tag: bytes, point: bytes) -> float | None:
    if len(point) != len(tag) + 8 or not point.startswith(tag):
        return None
    (value,) = struct.unpack("<d", point[len(tag):])
    return float(value)


class GatewayHistory(HistoryManager):  # type: ignore[misc]  # (asyncua is Any to mypy)
    """HistoryRead of the measured variables, ``variables`` mapping each one's NodeId
    to its (sensor, field).  Continuation points are stateless (where the next page
    starts), so releasing one frees nothing and no client can exhaust them."""

    def __init__(self, iserver: InternalServer, history: History,
                 variables: Mapping[ua.NodeId, tuple[str, str]]) -> None:
        super().__init__(iserver)
        self.history, self.variables = history, dict(variables)

    async def read_history(self, params: ua.HistoryReadParameters) -> list[ua.HistoryReadResult]:
        stamps = params.TimestampsToReturn
        if stamps not in (ua.TimestampsToReturn.Source, ua.TimestampsToReturn.Server,
                          ua.TimestampsToReturn.Both):
            raise ServiceError(ua.StatusCodes.BadTimestampsToReturnInvalid)
        details, nodes = params.HistoryReadDetails, params.NodesToRead
        if params.ReleaseContinuationPoints:  # (stateless: nothing to free)
            return [ua.HistoryReadResult() for _ in nodes]
        if isinstance(details, ua.ReadProcessedDetails) \
                and len(details.AggregateType) != len(nodes):
            return [_bad("BadAggregateListMismatch") for _ in nodes]
        results = [self._read(details, rv, i) for i, rv in enumerate(nodes)]
        if stamps is not ua.TimestampsToReturn.Both:
            for result in results:
                data = getattr(result.HistoryData, "DataValues", [])
                data[:] = [_stamped(dv, stamps) for dv in data]
        return results

    async def _read_history(self, details: Any, rv: ua.HistoryReadValueId) -> ua.HistoryReadResult:
        return self._read(details, rv, 0)  # (asyncua's own entry point, one node)

    def _read(self, details: Any, rv: ua.HistoryReadValueId, i: int) -> ua.HistoryReadResult:
        where = self.variables.get(rv.NodeId)
        if where is None:
            known = rv.NodeId in self.iserver.aspace
            return _bad("BadHistoryOperationUnsupported" if known else "BadNodeIdUnknown")
        seconds = self.history.seconds(*where)
        if isinstance(details, ua.ReadRawModifiedDetails):
            if details.IsReadModified:  # nothing kept is ever modified: none to give
                return ua.HistoryReadResult(HistoryData=ua.HistoryModifiedData())
            return self._raw(details, rv, seconds)
        if isinstance(details, ua.ReadProcessedDetails):
            return self._processed(details, rv, seconds, details.AggregateType[i])
        return _bad("BadHistoryOperationUnsupported")  # events, at-time, annotations

    def _raw(self, details: ua.ReadRawModifiedDetails, rv: ua.HistoryReadValueId,
             seconds: Sequence[Second]) -> ua.HistoryReadResult:
        start, end = _epoch(details.StartTime), _epoch(details.EndTime)
        if start is None and end is None:
            return _bad("BadInvalidTimestampArgument")
        if start is None:  # Part 11: from EndTime backwards
            first, last, reverse = end, None, True
        else:
            first, last, reverse = start, end, end is not None and end < start
        assert first is not None
        first_bound = True
        if rv.ContinuationPoint:
            resume = _unpack(_RAW_POINT, rv.ContinuationPoint)
            if resume is None:
                return _bad("BadContinuationPointInvalid")
            first, first_bound = resume, False
        picked = raw_range(raw_points(seconds), first, last, reverse=reverse,
                           bounds=details.ReturnBounds, first_bound=first_bound)
        limit = details.NumValuesPerNode or len(picked)
        more = picked[limit].at if limit < len(picked) else None
        values = [_value(p.at, p.value, "Double", ua.StatusCodes.Good, "BadBoundNotFound")
                  for p in picked[:limit]]
        return ua.HistoryReadResult(
            HistoryData=ua.HistoryData(DataValues=values),
            ContinuationPoint=None if more is None else _pack(_RAW_POINT, more))

    def _processed(self, details: ua.ReadProcessedDetails, rv: ua.HistoryReadValueId,
                   seconds: Sequence[Second], aggregate: ua.NodeId) -> ua.HistoryReadResult:
        kind = next((a for a in Aggregate if ua.NodeId(a.value) == aggregate), None)
        if kind is None:
            return _bad("BadAggregateNotSupported")
        start, end = _epoch(details.StartTime), _epoch(details.EndTime)
        if start is None or end is None or end < start:
            return _bad("BadInvalidTimestampArgument")
        step = details.ProcessingInterval / 1000.0
        if step < 0 or step != math.floor(step):  # whole seconds, as the buckets are
            return _bad("BadInvalidArgument")
        first = 0
        if rv.ContinuationPoint:
            resume = _unpack(_PROCESSED_POINT, rv.ContinuationPoint)
            if resume is None:
                return _bad("BadContinuationPointInvalid")
            first = int(resume)
        intervals, more = processed(kind, seconds, start, end, step, first)
        kind_bits = _INTERPOLATED if kind is Aggregate.INTERPOLATIVE else _CALCULATED
        values = [_value(x.start, x.value, "Double",
                         _DATA_VALUE | kind_bits | (_PARTIAL if x.partial else 0), "BadNoData")
                  for x in intervals]
        return ua.HistoryReadResult(
            HistoryData=ua.HistoryData(DataValues=values),
            ContinuationPoint=None if more is None else _pack(_PROCESSED_POINT, more))


def _value(at: float, value: float | None, datatype: str, good: int,
           missing: str) -> ua.DataValue:
    """A history DataValue: both timestamps the value's time (the gateway stamps a
    sample when it comes off the wire, so its server time is its source time)."""
    moment = datetime.fromtimestamp(at, UTC)
    if value is None:
        return ua.DataValue(StatusCode=ua.StatusCode(getattr(ua.StatusCodes, missing)),
                            SourceTimestamp=moment, ServerTimestamp=moment)
    return ua.DataValue(ua.Variant(value, getattr(ua.VariantType, datatype)),
                        StatusCode=ua.StatusCode(good), SourceTimestamp=moment,
                        ServerTimestamp=moment)


def _stamped(dv: ua.DataValue, stamps: ua.TimestampsToReturn) -> ua.DataValue:
    """``dv`` with only the timestamp asked for."""
    source = stamps is ua.TimestampsToReturn.Source
    return ua.DataValue(dv.Value, StatusCode=dv.StatusCode,
                        SourceTimestamp=dv.SourceTimestamp if source else None,
                        ServerTimestamp=None if source else dv.ServerTimestamp)


async def install(server: Server, history: History,
                  variables: Mapping[ua.NodeId, tuple[str, str]]) -> GatewayHistory:
    """Serve HistoryRead from ``history`` and say so in the Server object's
    HistoryServerCapabilities and AggregateFunctions (clients read them first).
    Returns the service, whose ``variables`` a reload changes."""
    manager = GatewayHistory(server.iserver, history, variables)
    server.iserver.history_manager = manager
    for node, value, kind in (
            (ua.ObjectIds.HistoryServerCapabilities_AccessHistoryDataCapability, True, "Boolean"),
            (ua.ObjectIds.HistoryServerCapabilities_ServerTimestampSupported, True, "Boolean"),
            (ua.ObjectIds.HistoryServerCapabilities_MaxReturnDataValues, MAX_INTERVALS,
             "UInt32")):
        await server.get_node(node).write_value(ua.Variant(value, getattr(ua.VariantType, kind)))
    for folder in (ua.ObjectIds.HistoryServerCapabilities_AggregateFunctions,
                   ua.ObjectIds.Server_ServerCapabilities_AggregateFunctions):
        have = {n.nodeid for n in await server.get_node(folder).get_children()}
        for aggregate in Aggregate:
            if ua.NodeId(aggregate.value) not in have:
                await server.get_node(folder).add_reference(
                    ua.NodeId(aggregate.value), ua.ObjectIds.Organizes, bidirectional=False)
    return manager


HISTORY_DOC = f"""## History

Every measured variable (`…Sensors.{{sensor}}.{{Group}}.{{field}}`) has
`Historizing = true` and the `HistoryRead` bit in its `AccessLevel` and
`UserAccessLevel`.  The gateway keeps, in memory, the last **{KEEP_S} s** ({KEEP_S // 60}
minutes) of every sensor, one bucket per second of wire time: per field the
second's lowest, highest and last value, the sum and the count of its values, and
the wire time of the second's last sample.  Nothing is kept across a restart.  NaN
values (a Modbus float register, a derived value that has none) are no values.
About 400 KB per sensor of 19 fields (an AH's 16 measured and 3 derived), fixed from
the start.

**HistoryReadRaw** (`ReadRawModifiedDetails`, `IsReadModified = false`) returns
each kept second's last value: `SourceTimestamp` and `ServerTimestamp` are both that
sample's wire time (the gateway stamps a sample when its answer comes off the bus),
StatusCode Good, DataType Double (the variable's).  Where a second's last sample had no value of a
field (NaN), the field's last value of that second is returned, stamped with the
time of the second's last sample.

- The range is `StartTime ≤ t < EndTime`.  `EndTime` before `StartTime` returns the
  values newest first (`EndTime < t ≤ StartTime`); no `StartTime` reads backwards
  from `EndTime`, no `EndTime` forwards from `StartTime`; neither is
  `BadInvalidTimestampArgument`.
- `ReturnBounds`: the value at or before the start (after it, in reverse) and the
  one at or after the end; a bound the history does not hold is a value with
  StatusCode `BadBoundNotFound` at the bound's time.
- `NumValuesPerNode` limits a response; the rest comes with a continuation point.
  Continuation points are stateless (they hold where the next page starts), so
  `ReleaseContinuationPoints` frees nothing and has nothing to refuse.
- `IsReadModified = true`: Good with no values (the gateway never modifies a value).

**HistoryReadProcessed** (`ReadProcessedDetails`) offers Part 13's **Minimum**,
**Maximum**, **Average** and **Interpolative**, also listed under the Server
object's `AggregateFunctions`:

- `ProcessingInterval` must be a whole number of seconds (1000 ms, 2000 ms, …) or 0
  (one interval for the whole range); anything else is `BadInvalidArgument`.
  `StartTime` and `EndTime` must both be given, `StartTime` first:
  otherwise `BadInvalidTimestampArgument`.
- Intervals start at `StartTime`; each value is stamped with its interval's start.
  Each second's bucket counts in the interval it begins in, so the values are exact
  when `StartTime` is on a whole second.
- Minimum and Maximum are the lowest and highest value of the interval,
  Average the mean of all its values (exact, from each second's sum and count); all
  three Double.  StatusCode Good with InfoType DataValue and the historian bit
  `Calculated` (`0x00000401`), plus `Partial` (`0x4`) for a last interval cut short
  by `EndTime`.
- Interpolative is the value at the interval's start, linear between the kept raw
  values around it (each second's last); Good with `Interpolated` (`0x00000402`).
  Where the history has no kept value on one side, `BadNoData`: the gateway does not
  extrapolate.
- An interval without data is `BadNoData`.  At most {MAX_INTERVALS} intervals per node
  in one response, the rest with a continuation point.
- Any other aggregate: `BadAggregateNotSupported` for that node; an
  `AggregateType` list not one per node: `BadAggregateListMismatch`.
- `AggregateConfiguration` is taken as the server's defaults whatever it says: every
  kept value is Good, so `TreatUncertainAsBad`, `PercentDataBad` and
  `PercentDataGood` change nothing, and nothing is extrapolated
  (`UseSlopedExtrapolation`).

HistoryRead of any other node: `BadHistoryOperationUnsupported` (an unknown node:
`BadNodeIdUnknown`); event history and `ReadAtTimeDetails` likewise
`BadHistoryOperationUnsupported`.  `TimestampsToReturn` Neither is
`BadTimestampsToReturnInvalid`.  HistoryUpdate is `BadNotWritable`.
"""
