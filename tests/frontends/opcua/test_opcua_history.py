"""OPC UA HistoryRead (docs/opcua.md "History"): the ring and the Part 11/13
arithmetic on their own (time an argument), then the real gateway on a simulated
sensor read with asyncua's client.  Expected values come from the samples the
gateway published (a cache listener of the test's own), never from the server."""

from __future__ import annotations

import math
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from asyncua import Client, ua
from support.harness import free_port, running, until

from imu_gateway.cache import EventKind, Snapshot
from imu_gateway.config import SensorConfig
from imu_gateway.frontends.opcua.history import (
    MAX_INTERVALS,
    Aggregate,
    Sample,
    interpolate,
    processed,
    raw_range,
)
from imu_gateway.history import KEEP_S, History, Second
from imu_gateway.model import Series, WireProtocol
from imu_gateway.normalise import field_values
from imu_gateway.simulator import make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "ua-hist"
NS = "urn:imu-gateway"
FIELD = "roll"
ROLL = f"{GID}.Sensors.boom.Angles.{FIELD}"
GOOD_CALCULATED, GOOD_INTERPOLATED = 0x401, 0x402
_STATUS = ua.StatusCodes


def _imu_history() -> History:
    return History(SimpleNamespace(sensors={"s": SensorConfig(name="s", series=Series.IMU,
                                                              address=0)}))


# ------------------------------------------------------------------ the ring


def test_each_second_keeps_its_sum_count_and_last_wire_time() -> None:
    history = _imu_history()
    n = len(history.fields["s"])
    for at, v in ((100.1, 1.0), (100.5, -2.0), (100.9, math.nan), (101.2, math.nan),
                  (101.7, 4.0), (99.5, 7.0)):  # (99.5: the clock stepped back a little)
        history.add("s", at, [v] * n)
    assert history.seconds("s", "accel_x") == [
        Second(100, 100.9, -2.0, 1.0, -2.0, -1.0, 2),  # NaN: no value, but the last sample
        Second(101, 101.7, 4.0, 4.0, 4.0, 4.0, 1)]
    assert history.query("s", 10, now=102.0)["fields"]["accel_x"]["last"] == [-2.0, 4.0]
    # a second comes back only as itself: the slot of 100 + KEEP_S replaces it
    history.add("s", 100.0 + KEEP_S, [5.0] * n)
    assert [s.start for s in history.seconds("s", "accel_x")] == [101, 100 + KEEP_S]
    # the clock far back (more than the ring holds): the ring starts again
    history.add("s", 50.25, [6.0] * n)
    assert history.seconds("s", "gyro_z") == [Second(50, 50.25, 6.0, 6.0, 6.0, 6.0, 1)]


def test_the_ring_is_fixed_and_small() -> None:
    history = _imu_history()
    before = history.nbytes
    for second in range(3 * KEEP_S):
        history.add("s", 1000.0 + second, [1.0] * 7)
    # 7 fields (6 measured, the vibration derived): 152 KB
    assert history.nbytes == before <= KEEP_S * (16 + 7 * 34)


# ------------------------------------------------------------------ the arithmetic


POINTS = [Sample(10.5, 1.0), Sample(11.5, 2.0), Sample(12.5, 3.0), Sample(13.5, 4.0)]


def _pairs(samples: list[Sample]) -> list[tuple[float, float | None]]:
    return [(s.at, s.value) for s in samples]


def test_raw_ranges_in_both_directions_with_bounds() -> None:
    forward = raw_range(POINTS, 11.5, 13.5, reverse=False, bounds=False)
    assert _pairs(forward) == [(11.5, 2.0), (12.5, 3.0)]  # start in, end out
    # Part 11: the bound at the start is the value there, else the one before it
    assert _pairs(raw_range(POINTS, 11.0, 13.5, reverse=False, bounds=True)) == [
        (10.5, 1.0), (11.5, 2.0), (12.5, 3.0), (13.5, 4.0)]
    assert _pairs(raw_range(POINTS, 11.5, 12.0, reverse=False, bounds=True)) == [
        (11.5, 2.0), (12.5, 3.0)]
    # bounds the history does not hold: no value, at the bound's time
    assert _pairs(raw_range(POINTS, 1.0, 20.0, reverse=False, bounds=True)) == [
        (1.0, None), *_pairs(POINTS), (20.0, None)]
    # EndTime before StartTime: newest first, start in, end out
    assert _pairs(raw_range(POINTS, 12.5, 10.5, reverse=True, bounds=False)) == [
        (12.5, 3.0), (11.5, 2.0)]
    assert _pairs(raw_range(POINTS, 13.0, 11.0, reverse=True, bounds=True)) == [
        (13.5, 4.0), (12.5, 3.0), (11.5, 2.0), (10.5, 1.0)]
    # no end: everything from the start; a continuation leaves the start bound out
    assert _pairs(raw_range(POINTS, 12.0, None, reverse=False, bounds=True,
                            first_bound=False)) == [(12.5, 3.0), (13.5, 4.0)]


def _second(start: int, values: list[float]) -> Second:
    return Second(start, start + 0.9, min(values), max(values), values[-1], sum(values),
                  len(values))


def test_aggregates_over_whole_seconds() -> None:
    seconds = [_second(100, [1.0, 5.0]), _second(101, [2.0]), _second(103, [-1.0, 0.0, 4.0])]
    minimum, _ = processed(Aggregate.MINIMUM, seconds, 100.0, 105.0, 2.0)
    assert [(x.start, x.value, x.partial) for x in minimum] == [
        (100.0, 1.0, False), (102.0, -1.0, False), (104.0, None, True)]
    maximum, _ = processed(Aggregate.MAXIMUM, seconds, 100.0, 104.0, 1.0)
    assert [x.value for x in maximum] == [5.0, 2.0, None, 4.0]
    average, _ = processed(Aggregate.AVERAGE, seconds, 100.0, 104.0, 0.0)  # one interval
    assert [x.value for x in average] == [pytest.approx(11.0 / 6)]  # the raw values' mean
    # Interpolative: at each interval's start, between the seconds' last values (at
    # 100.9, 101.9 and 103.9): none before the first
    inter, _ = processed(Aggregate.INTERPOLATIVE, seconds, 100.0, 104.0, 1.0)
    assert [x.value for x in inter] == [None, pytest.approx(5.0 - 3.0 * 0.1),
                                        pytest.approx(2.0 + 2.0 * 0.1 / 2),
                                        pytest.approx(2.0 + 2.0 * 1.1 / 2)]
    assert interpolate([Sample(1.0, 2.0)], 1.0) == 2.0
    # paging: at most ``limit`` intervals, and where the next page starts
    page, more = processed(Aggregate.MAXIMUM, seconds, 100.0, 104.0, 1.0, first=1, limit=2)
    assert ([x.start for x in page], more) == ([101.0, 102.0], 3)
    assert processed(Aggregate.MAXIMUM, seconds, 100.0, 104.0, 1.0, first=3)[1] is None


# ------------------------------------------------------------------ the real gateway


def _config(port: int, pki: Path, line: str) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": line, "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "poll_hz": 20}]}],
            "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": str(pki), "allow_none": True}}


@pytest.fixture
def line() -> Iterator[str]:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200,
                         source=Motion.from_seed(5))
    with simulated([sensor]) as sim:
        yield sim.path


class Published:
    """Every sample the gateway published, as its cache gave it: (wire time, value)."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, float]] = []

    def __call__(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.READING and snap.reading is not None and snap.timestamp:
            self.rows.append((snap.timestamp.timestamp(), field_values(snap.reading)[FIELD]))

    def after(self, moment: float) -> bool:
        return bool(self.rows) and self.rows[-1][0] >= moment


def _time(epoch: float) -> datetime:
    return datetime.fromtimestamp(epoch, UTC)


def _params(details: Any, nodes: list[ua.NodeId], point: bytes | None = None,
            ) -> ua.HistoryReadParameters:
    params = ua.HistoryReadParameters()
    params.HistoryReadDetails = details
    params.TimestampsToReturn = ua.TimestampsToReturn.Both
    params.ReleaseContinuationPoints = False  # (asyncua's default is True)
    params.NodesToRead = [ua.HistoryReadValueId(NodeId=n, ContinuationPoint=point)
                          for n in nodes]
    return params


def _processed(start: float, end: float, interval_ms: float,
               aggregates: list[int]) -> ua.ReadProcessedDetails:
    details = ua.ReadProcessedDetails()
    details.StartTime, details.EndTime = _time(start), _time(end)
    details.ProcessingInterval = interval_ms
    details.AggregateType = [ua.NodeId(a) for a in aggregates]
    return details


def _raw(start: float, end: float, count: int = 0, bounds: bool = False,
         ) -> ua.ReadRawModifiedDetails:
    return ua.ReadRawModifiedDetails(IsReadModified=False, StartTime=_time(start),
                                     EndTime=_time(end), NumValuesPerNode=count,
                                     ReturnBounds=bounds)


@pytest.mark.anyio
async def test_history_read_serves_what_the_gateway_kept(tmp_path: Path, line: str) -> None:
    """Raw: each kept second's last sample, at its wire time; processed Minimum,
    Maximum, Average over 1 s and 2 s equal a recomputation from the published samples,
    Interpolative the line between the raw values."""
    port = free_port()
    async with running(_config(port, tmp_path / "pki", line)) as gw:
        published = Published()
        gw.cache.subscribe(published)
        await until(lambda: bool(published.rows))  # (a first sample)
        t0 = math.ceil(published.rows[0][0]) + 1  # the first whole second seen whole
        await until(lambda: published.after(t0 + 4), timeout=30)  # (seconds must pass)
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index(NS)
            roll = client.get_node(ua.NodeId(ROLL, idx))
            assert (await roll.read_attribute(ua.AttributeIds.Historizing)).Value.Value is True
            level = (await roll.read_attribute(ua.AttributeIds.AccessLevel)).Value.Value
            user = (await roll.read_attribute(ua.AttributeIds.UserAccessLevel)).Value.Value
            readable = ua.AccessLevel.CurrentRead.mask | ua.AccessLevel.HistoryRead.mask
            assert level == user == readable

            raw = await roll.read_raw_history(_time(t0), _time(t0 + 4), return_bounds=False)
            # the last sample the gateway published in each second, at its wire time
            last: dict[int, tuple[float, float]] = {}
            for at, value in published.rows:
                if t0 <= at < t0 + 4:
                    last[math.floor(at)] = (at, value)
            assert [math.floor(dv.SourceTimestamp.timestamp()) for dv in raw] == sorted(last)
            for dv, (at, value) in zip(raw, [last[k] for k in sorted(last)], strict=True):
                assert dv.StatusCode.value == _STATUS.Good
                assert abs(dv.SourceTimestamp.timestamp() - at) < 1e-6
                assert dv.ServerTimestamp == dv.SourceTimestamp
                assert dv.Value.Value == value  # as the sensor gave it, not a float32's
                assert dv.Value.VariantType == ua.VariantType.Double

            for interval in (1, 2):
                await _check_processed(client, roll.nodeid, published, t0, interval, raw)


async def _check_processed(client: Client, node: ua.NodeId, published: Published, t0: int,
                           interval: int, raw: list[ua.DataValue]) -> None:
    kinds = [ua.ObjectIds.AggregateFunction_Minimum, ua.ObjectIds.AggregateFunction_Average,
             ua.ObjectIds.AggregateFunction_Maximum, ua.ObjectIds.AggregateFunction_Interpolative]
    details = _processed(t0, t0 + 4, interval * 1000.0, kinds)
    low, mean, high, inter = await client.uaclient.history_read(_params(details, [node] * 4))
    for k, (a, m, b) in enumerate(zip(low.HistoryData.DataValues, mean.HistoryData.DataValues,
                                      high.HistoryData.DataValues, strict=True)):
        start = t0 + k * interval
        values = [v for at, v in published.rows if start <= at < start + interval]
        assert values, "a whole second without a sample: the poll fell far behind"
        for dv in (a, m, b):
            assert dv.StatusCode.value == GOOD_CALCULATED
            assert dv.SourceTimestamp == _time(start)
        assert a.Value.Value <= m.Value.Value <= b.Value.Value
        assert (a.Value.Value, b.Value.Value) == (min(values), max(values))
        assert {a.Value.VariantType, m.Value.VariantType, b.Value.VariantType} == {
            ua.VariantType.Double}
        assert m.Value.Value == pytest.approx(math.fsum(values) / len(values), rel=1e-12)
    assert len(low.HistoryData.DataValues) == 4 // interval
    # Interpolative: between the raw values around each interval's start
    points = [Sample(dv.SourceTimestamp.timestamp(), dv.Value.Value) for dv in raw]
    for k, dv in enumerate(inter.HistoryData.DataValues):
        expected = interpolate(points, t0 + k * interval)
        if expected is None:  # the start precedes the first raw value read
            continue
        assert dv.StatusCode.value == GOOD_INTERPOLATED
        assert dv.Value.Value == pytest.approx(expected, abs=1e-4)


@pytest.mark.anyio
async def test_continuation_points_bounds_and_reverse(tmp_path: Path, line: str) -> None:
    port = free_port()
    async with running(_config(port, tmp_path / "pki", line)) as gw:
        published = Published()
        gw.cache.subscribe(published)
        # (seconds must pass: a deadline well past them)
        await until(lambda: len(gw.history.seconds("boom", FIELD)) >= 5, timeout=30)
        kept = gw.history.seconds("boom", FIELD)[:4]  # seconds over: no sample will change
        start, end = kept[0].at, kept[3].at
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            node = ua.NodeId(ROLL, await client.get_namespace_index(NS))
            (whole,) = await client.uaclient.history_read(_params(_raw(start, end), [node]))
            assert [dv.SourceTimestamp.timestamp() for dv in whole.HistoryData.DataValues] \
                == pytest.approx([s.at for s in kept[:3]], abs=1e-6)
            pages, point = [], None
            for _ in range(10):
                (page,) = await client.uaclient.history_read(
                    _params(_raw(start, end, count=2), [node], point))
                assert len(page.HistoryData.DataValues) <= 2
                pages += page.HistoryData.DataValues
                point = page.ContinuationPoint
                if not point:
                    break
            assert pages == whole.HistoryData.DataValues
            (bad,) = await client.uaclient.history_read(
                _params(_raw(start, end), [node], b"not ours"))
            assert bad.StatusCode.value == _STATUS.BadContinuationPointInvalid
            # reverse, with bounds: the one before the first kept is not kept
            (back,) = await client.uaclient.history_read(
                _params(_raw(end, start - 30, bounds=True), [node]))
            got = back.HistoryData.DataValues
            assert [dv.SourceTimestamp.timestamp() for dv in got[:-1]] \
                == pytest.approx([s.at for s in reversed(kept)], abs=1e-6)
            assert got[-1].StatusCode.value == _STATUS.BadBoundNotFound
            # processed: more intervals than one answer holds
            last = kept[2].start + 1  # (the last interval: kept[2]'s second)
            details = _processed(last - 1500, last, 1000.0,
                                 [ua.ObjectIds.AggregateFunction_Maximum])
            (first,) = await client.uaclient.history_read(_params(details, [node]))
            assert len(first.HistoryData.DataValues) == MAX_INTERVALS
            assert first.HistoryData.DataValues[0].StatusCode.value == _STATUS.BadNoData
            (rest,) = await client.uaclient.history_read(
                _params(details, [node], first.ContinuationPoint))
            assert len(rest.HistoryData.DataValues) == 1500 - MAX_INTERVALS
            assert rest.ContinuationPoint is None
            assert rest.HistoryData.DataValues[-1].StatusCode.value == GOOD_CALCULATED


@pytest.mark.anyio
async def test_what_history_read_refuses(tmp_path: Path, line: str) -> None:
    """Each refusal names its cause for its node only; the others are served."""
    port = free_port()
    async with running(_config(port, tmp_path / "pki", line)) as gw:
        await until(lambda: len(gw.history.seconds("boom", FIELD)) >= 2, timeout=30)
        end = gw.history.seconds("boom", FIELD)[-1].start
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index(NS)
            roll = ua.NodeId(ROLL, idx)
            series = ua.NodeId(f"{GID}.Sensors.boom.Series", idx)  # not historized
            nobody = ua.NodeId(f"{GID}.Sensors.nobody.Angles.roll", idx)
            raw = await client.uaclient.history_read(
                _params(_raw(end - 10, end), [series, nobody, roll]))
            assert [r.StatusCode.value for r in raw] == [
                _STATUS.BadHistoryOperationUnsupported, _STATUS.BadNodeIdUnknown, _STATUS.Good]
            assert raw[2].HistoryData.DataValues
            count = ua.ObjectIds.AggregateFunction_Count  # not offered
            mixed = await client.uaclient.history_read(_params(_processed(
                end - 2, end, 1000.0, [count, ua.ObjectIds.AggregateFunction_Minimum]),
                [roll, roll]))
            assert [r.StatusCode.value for r in mixed] == [
                _STATUS.BadAggregateNotSupported, _STATUS.Good]
            for interval in (1500.0, 500.0, -1000.0):
                (odd,) = await client.uaclient.history_read(_params(_processed(
                    end - 2, end, interval, [ua.ObjectIds.AggregateFunction_Minimum]), [roll]))
                assert odd.StatusCode.value == _STATUS.BadInvalidArgument, interval
            (backwards,) = await client.uaclient.history_read(_params(_processed(
                end, end - 2, 1000.0, [ua.ObjectIds.AggregateFunction_Minimum]), [roll]))
            assert backwards.StatusCode.value == _STATUS.BadInvalidTimestampArgument
            mismatch = await client.uaclient.history_read(_params(_processed(
                end - 2, end, 1000.0, [ua.ObjectIds.AggregateFunction_Minimum]), [roll, roll]))
            assert [r.StatusCode.value for r in mismatch] == [
                _STATUS.BadAggregateListMismatch] * 2
            modified = _raw(end - 10, end)
            modified.IsReadModified = True
            (none,) = await client.uaclient.history_read(_params(modified, [roll]))
            assert none.StatusCode.value == _STATUS.Good and not none.HistoryData.DataValues
            # the server says what it offers
            functions = client.get_node(ua.ObjectIds.HistoryServerCapabilities_AggregateFunctions)
            offered = {n.nodeid.Identifier for n in await functions.get_children()}
            assert {ua.ObjectIds.AggregateFunction_Minimum,
                    ua.ObjectIds.AggregateFunction_Maximum,
                    ua.ObjectIds.AggregateFunction_Average,
                    ua.ObjectIds.AggregateFunction_Interpolative} <= offered
            access = client.get_node(
                ua.ObjectIds.HistoryServerCapabilities_AccessHistoryDataCapability)
            assert await access.read_value() is True
