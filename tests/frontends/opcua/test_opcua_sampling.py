"""Monitored items' sampling intervals (docs/opcua.md, "Monitored items' sampling";
OPC UA Part 4 5.12.1.2), from a client's side: a 50 Hz sensor (the simulator), items
of one subscription (publishing interval 100 ms) at sampling 0 (every sample), 200 ms
and -1 (the publishing interval); a Modify; a stalled sensor's bad status under a
1000 ms item.  The server's answers are read as sent (asyncua's client keeps the
revised intervals of a Create to itself, so its call is wrapped to see them)."""

from __future__ import annotations

import statistics
from collections import defaultdict
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from support.harness import free_port, running, until

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

GID = "ua-sampling"
NS = "urn:imu-gateway"
PUBLISHING_MS = 100.0
SAMPLE_S = 1 / 50  # the sensor's period
#: what a sampled value's SourceTimestamp may come short of the interval by: one sample
#: period, and the wobble of the poll's and the write's times on a busy machine
SLACK_S = 0.05


@pytest.fixture
def line() -> Iterator[tuple[str, Faults]]:
    faults = Faults()
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200,
                     source=hold(Motion.from_seed(3).sample(1.0)), faults=faults)
    with simulated([ah]) as sim:
        yield sim.path, faults


def _config(port: int, pki: Path, path: str) -> dict[str, Any]:
    return {"gateway_id": GID,
            "buses": [{"name": "a", "port": path, "baudrate": 115200, "protocol": "native",
                       "timeout_ms": 300,
                       "sensors": [{"name": "boom", "series": "AH", "poll_hz": 50,
                                    "stale_after_ms": 400}]}],
            "opcua": {"listen": f"127.0.0.1:{port}", "pki_dir": str(pki),
                      "allow_none": True}}


class Told:
    """What each monitored item (by client handle) was told, and when it came."""

    def __init__(self) -> None:
        self.of: dict[int, list[tuple[datetime, ua.DataValue]]] = defaultdict(list)

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        item = data.monitored_item
        self.of[item.ClientHandle].append((datetime.now(UTC), item.Value))

    def values(self, handle: int) -> list[Any]:
        return [dv.Value.Value for _, dv in self.of[handle]]

    def gaps(self, handle: int) -> list[float]:
        """Seconds between the SourceTimestamps of the item's values after its first
        (the initial value, reported at once).  Their median is held to the interval, not
        each one: a sample's SourceTimestamp is when the bus got it, and on a busy
        machine a tick can find the newest sample one late and the next tick one on time
        (gaps of 0.12 s and 0.45 s at 200 ms, beside other test runs)."""
        stamps = [dv.SourceTimestamp for _, dv in self.of[handle]][1:]
        return [(b - a).total_seconds() for a, b in pairwise(stamps)]


def _watch(handle: int, node: ua.NodeId, sampling: float,
           queue: int = 1) -> ua.MonitoredItemCreateRequest:
    return ua.MonitoredItemCreateRequest(
        ItemToMonitor=ua.ReadValueId(NodeId=node, AttributeId=ua.AttributeIds.Value),
        MonitoringMode=ua.MonitoringMode.Reporting,
        RequestedParameters=ua.MonitoringParameters(
            ClientHandle=handle, SamplingInterval=sampling, QueueSize=queue,
            DiscardOldest=True))


async def _subscribe(client: Client, told: Told, items: list[ua.MonitoredItemCreateRequest],
                     publishing: float = PUBLISHING_MS) -> tuple[Any, list[Any]]:
    """A subscription of ``publishing`` ms with ``items``; the server's results."""
    subscription = await client.create_subscription(publishing, told)
    made: list[Any] = []
    session = subscription.server  # (the session's calls, which the subscription makes)
    create = session.create_monitored_items

    async def seen(params: ua.CreateMonitoredItemsParameters) -> list[Any]:
        results: list[Any] = await create(params)
        made.extend(results)
        return results

    session.create_monitored_items = seen
    try:
        await subscription.create_monitored_items(items)
    finally:
        del session.create_monitored_items  # (the class's again)
    assert all(m.StatusCode.is_good() for m in made), made
    return subscription, made


def _modify(subscription: Any, item: int, sampling: float,
            queue: int = 1) -> ua.ModifyMonitoredItemsParameters:
    return ua.ModifyMonitoredItemsParameters(
        SubscriptionId=subscription.subscription_id, ItemsToModify=[
            ua.MonitoredItemModifyRequest(MonitoredItemId=item, RequestedParameters=(
                ua.MonitoringParameters(ClientHandle=9, SamplingInterval=sampling,
                                        QueueSize=queue)))])


def _nodes(idx: int, *paths: str) -> list[ua.NodeId]:
    return [ua.NodeId(f"{GID}.Sensors.boom.{p}", idx) for p in paths]


@dataclass
class Watching:
    """A gateway, a client, and its subscription of one item of the sensor's."""

    gw: Gateway
    client: Client
    node: ua.NodeId
    subscription: Any
    item: Any  # the item's create result
    told: Told


@asynccontextmanager
async def watching(tmp_path: Path, path: str, sampling: float, node: str = "Sequence",
                   publishing: float = PUBLISHING_MS) -> AsyncIterator[Watching]:
    port = free_port()
    async with running(_config(port, tmp_path / "pki", path)) as gw, \
            Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        await until(lambda: gw.cache.snapshot("boom").seq >= 2)
        idx = await client.get_namespace_index(NS)
        (watched,) = _nodes(idx, node)
        told = Told()
        subscription, made = await _subscribe(client, told, [_watch(1, watched, sampling)],
                                              publishing=publishing)
        yield Watching(gw, client, watched, subscription, made[0], told)


@pytest.mark.anyio
async def test_each_item_is_sampled_at_its_revised_interval(
        tmp_path: Path, line: tuple[str, Faults]) -> None:
    """0: every sample (consecutive Sequence numbers); 200 ms: revised 200, values at
    least ~200 ms apart (asyncua answered the publishing interval and sent every
    sample: with a queue of one, one value at each 100 ms publish); -1: the
    publishing interval; a tiny or odd interval: a multiple of 10 ms.  A Read still
    gives the newest sample."""
    port = free_port()
    async with running(_config(port, tmp_path / "pki", line[0])) as gw, \
            Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        await until(lambda: gw.cache.snapshot("boom").seq >= 2)
        idx = await client.get_namespace_index(NS)
        (sequence,) = _nodes(idx, "Sequence")
        told = Told()
        subscription, made = await _subscribe(client, told, [
            _watch(1, sequence, 0.0, queue=100), _watch(2, sequence, 200.0),
            _watch(3, sequence, -1.0), _watch(4, sequence, 0.001), _watch(5, sequence, 15.0)])
        assert [m.RevisedSamplingInterval for m in made] == \
            [0.0, 200.0, PUBLISHING_MS, 10.0, 20.0]  # (multiples of 10 ms, rounded up)
        await until(lambda: len(told.of[2]) >= 8, 20)
        every = told.values(1)
        assert all(b == a + 1 for a, b in pairwise(every)), every
        assert gw.opcua is not None and gw.opcua._samples._telling is None  # (no task: tell_now)
        assert not gw.cache.prompt  # (OPC UA catches up when it reads, publishes, samples)
        sampled = told.values(2)
        assert sampled == sorted(set(sampled)) and set(sampled) <= set(every) | {every[-1] + 1}
        gaps = told.gaps(2)
        assert statistics.median(gaps) >= 0.2 - SLACK_S, gaps
        assert len(told.of[3]) >= 2  # (the publishing interval's: within 100 ms)
        newest = gw.cache.snapshot("boom").seq
        assert await client.get_node(sequence).read_value() >= newest  # a fresh Read
        await subscription.delete()


@pytest.mark.anyio
async def test_a_modify_changes_the_interval(tmp_path: Path, line: tuple[str, Faults]) -> None:
    """An item at 200 ms modified to 500 ms is answered 500 and sampled so; then to 0,
    every sample; an item that is not there is BadMonitoredItemIdInvalid (asyncua's
    own answer to it was a TypeError, the whole request's fault)."""
    async with watching(tmp_path, line[0], 200.0) as w:
        subscription, told, item = w.subscription, w.told, w.item.MonitoredItemId
        changed = await subscription.server.modify_monitored_items(
            _modify(subscription, item, 500))
        assert [c.RevisedSamplingInterval for c in changed] == [500.0]
        told.of[1].clear()
        await until(lambda: len(told.of[1]) >= 5, 20)
        gaps = told.gaps(1)
        assert statistics.median(gaps) >= 0.5 - SLACK_S, gaps
        changed = await subscription.server.modify_monitored_items(
            _modify(subscription, item, 0.0, queue=100))
        assert [c.RevisedSamplingInterval for c in changed] == [0.0]
        seen = len(told.of[1])
        await until(lambda: len(told.of[1]) >= seen + 20, 20)
        # the first is the one held at the Modify (older by any number), never after a
        # newer one; then each one
        every = told.values(1)[seen:]
        assert every[0] < every[1], every[:2]
        every = every[1:]
        assert all(b == a + 1 for a, b in pairwise(every)), every
        wrong = await subscription.server.modify_monitored_items(
            _modify(subscription, 4242, 50))
        assert [w.StatusCode.value for w in wrong] == [ua.StatusCodes.BadMonitoredItemIdInvalid]
        await subscription.delete()


@pytest.mark.anyio
async def test_a_stalled_sensors_bad_status_reaches_a_slow_item_within_its_interval(
        tmp_path: Path, line: tuple[str, Faults]) -> None:
    """A sensor that stops answering is written once as stale, once as offline, then
    never again: an item sampled every 1000 ms still gets the bad status, at most about
    one interval (and a publish) after it was written, though nothing is written after
    it."""
    path, faults = line
    async with watching(tmp_path, path, 1000.0, node="Angles.pitch") as w:
        subscription, told = w.subscription, w.told
        assert w.item.RevisedSamplingInterval == 1000.0
        await until(lambda: len(told.of[1]) >= 1, 10)  # the initial value (a held reading)
        faults.stalled = True

        def bad() -> tuple[datetime, ua.DataValue] | None:
            return next(((came, dv) for came, dv in told.of[1]
                         if dv.StatusCode.value == ua.StatusCodes.BadCommunicationError), None)

        await until(lambda: bad() is not None, 30)
        found = bad()
        assert found is not None
        came, value = found
        late = came - value.ServerTimestamp  # written (the server's clock is this one's)
        assert late <= timedelta(seconds=1.0 + PUBLISHING_MS / 1000 + 1.0), late
        await subscription.delete()


class Writes:
    """How many samples the server wrote into the sensor's nodes, and how many times
    it wrote what it held because a client looked (``writes.Samples``)."""

    def __init__(self, samples: Any) -> None:
        self.samples = samples
        self.written = self.flushes = 0
        self.selected: list[int] = []  # how many of the sensor's nodes each write wrote
        write, flush = samples._write, samples.flush

        def counted_write(snap: Any, which: Any = None) -> Any:
            self.written += 1
            nodes = [node for name, node in samples._nodes() if name == snap.name]
            self.selected.append(sum(1 for node in nodes if which is None or which.takes(node)))
            return write(snap, which)

        def counted_flush() -> None:
            self.flushes += 1
            flush()

        samples._write, samples.flush = counted_write, counted_flush

    async def over(self, gw: Any, samples: int) -> tuple[int, int, int]:
        """(samples that came, written, flushes) while ``samples`` came."""
        seq, written, flushes = gw.cache.snapshot("boom").seq, self.written, self.flushes
        await until(lambda: gw.cache.snapshot("boom").seq >= seq + samples, 30)
        gw.cache.catch_up()
        return (gw.cache.snapshot("boom").seq - seq, self.written - written,
                self.flushes - flushes)


@pytest.mark.anyio
async def test_a_sensor_is_written_when_a_client_looks_unless_an_item_takes_every_value(
        tmp_path: Path, line: tuple[str, Faults]) -> None:
    """With one item sampled every second (publishing every second), the 50 Hz
    sensor's samples are written only when a client looks (a publish, a tick, a
    request: at most one each), far fewer than came, and a Read still gives the
    newest.  Modified to sampling 0, each sample
    is written as it comes into that item's node (the sensor's others still when a
    client looks), and told in order; deleted, it is back to when a client looks."""
    port = free_port()
    async with running(_config(port, tmp_path / "pki", line[0])) as gw, \
            Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        await until(lambda: gw.cache.snapshot("boom").seq >= 2)
        assert gw.opcua is not None
        writes = Writes(gw.opcua._samples)
        idx = await client.get_namespace_index(NS)
        (sequence,) = _nodes(idx, "Sequence")
        told = Told()
        subscription, made = await _subscribe(client, told, [_watch(1, sequence, 1000.0)],
                                              publishing=1000.0)
        came, written, flushes = await writes.over(gw, 50)
        assert written <= flushes and written < came / 2, (came, written, flushes)
        newest = gw.cache.snapshot("boom").seq
        assert await client.get_node(sequence).read_value() >= newest  # a fresh Read

        changed = await subscription.server.modify_monitored_items(
            _modify(subscription, made[0].MonitoredItemId, 0.0, queue=100))
        assert [c.RevisedSamplingInterval for c in changed] == [0.0]
        seen = len(told.of[1])
        first = len(writes.selected)
        came, written, _ = await writes.over(gw, 50)
        assert written >= came, (came, written)  # (each one; a flush may add one more)
        # each into the one node taken every value of; the sensor's others when a
        # client looks, as before
        selected = writes.selected[first:]
        assert selected.count(1) >= came and max(selected) > 1, selected
        await until(lambda: len(told.of[1]) >= seen + 41, 20)  # (published every second)
        # the first is the one held at the Modify (older by any number), never after a
        # newer one; then each one
        every = told.values(1)[seen:]
        assert every[0] < every[1], every[:2]
        every = every[1:]
        assert len(every) >= 40 and all(b == a + 1 for a, b in pairwise(every)), every

        await subscription.delete()
        came, written, flushes = await writes.over(gw, 50)
        assert written <= flushes and written < came, (came, written, flushes)
        newest = gw.cache.snapshot("boom").seq
        assert await client.get_node(sequence).read_value() >= newest  # (the Read's look)


@pytest.mark.anyio
async def test_a_value_held_at_a_modify_to_zero_is_queued_before_any_newer(
        tmp_path: Path, line: tuple[str, Faults]) -> None:
    """An item sampled every second holds a value; a Modify to 0 and a newer value
    written in the same turn of the loop (nothing awaited between): the held one is
    queued first, and both are told in that order."""
    async with watching(tmp_path, line[0], 1000.0) as w:
        gw, subscription, told = w.gw, w.subscription, w.told
        assert gw.opcua is not None and gw.opcua.server is not None
        [isub] = gw.opcua.server.iserver.subscription_service.subscriptions.values()
        items = isub.monitored_item_srv
        mid = w.item.MonitoredItemId
        handle = items._monitored_items[mid].callback_handle
        held, newer = (ua.DataValue(ua.Variant(n, ua.VariantType.UInt32))
                       for n in (4_000_000, 4_000_001))
        items._held[handle] = held
        items._modify(_modify(subscription, mid, 0.0, queue=100))
        assert items.datachange_now(handle, newer)
        queued = [n.Value.Value.Value for n in isub._triggered_datachanges[mid]]
        assert queued[-2:] == [4_000_000, 4_000_001], queued
        await until(lambda: 4_000_001 in told.values(1), 10)
        values = told.values(1)
        assert values.index(4_000_000) == values.index(4_000_001) - 1, values
        await subscription.delete()
