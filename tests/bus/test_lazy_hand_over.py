"""The bus thread's turns reach the main loop lazily when nobody pushes (issue 29).

With only Modbus TCP and REST on, which read on demand, the main loop is not woken for
every exchange: the turns wait until something reads the cache (``Cache.catch_up``), or
``LAZY_HAND_OVER`` at the latest.  A listener that pushes to the outside, an open SSE
stream, or a turn that answers someone waiting makes the hand-over immediate again.
Each sample keeps its own times however late it is applied.

The writer's side is played in one thread, as in ``test_bus_thread``; the readers are
the gateway's own Modbus TCP server and REST app, as a client calls them."""

from __future__ import annotations

import asyncio
import csv
import io
import json
import math
import time
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import httpx
import pytest
from asyncua import Client, ua
from asyncua.server.address_space import AttributeValue, NodeData
from support.harness import free_port, until

from imu_gateway.app import Gateway
from imu_gateway.bus import reactor as reactor_module
from imu_gateway.bus import runner
from imu_gateway.bus.reactor import Reactor
from imu_gateway.bus.runner import CacheWriter
from imu_gateway.cache import Cache, EventKind, Snapshot
from imu_gateway.capture.ring import SensorRing
from imu_gateway.config import config_from_dict
from imu_gateway.errors import ErrorKind, RequestFailed
from imu_gateway.frontends.opcua.writes import DirectWriter, tell
from imu_gateway.frontends.rest.routes import create_app
from imu_gateway.frontends.rest.streams import StreamHub
from imu_gateway.model import Angles, KnownSettings, Reading, Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

READ_FLOATS = bytes((0x03, 0, 100, 0, 6))  # FC03, registers 100-105: pitch, roll, yaw
TARGET_FAILED = 0x0B


def reading(pitch: float) -> Reading:
    return Reading(angles=Angles(pitch, 0.0, 0.0))


@contextmanager
def wake_ups(loop: asyncio.AbstractEventLoop) -> Iterator[list[str]]:
    """The callbacks other threads asked the loop to run (each one a wake-up)."""
    asked: list[str] = []
    real = loop.call_soon_threadsafe

    def counted(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> asyncio.Handle:
        asked.append(fn.__name__)
        return real(fn, *args, **kwargs)

    loop.call_soon_threadsafe = counted  # type: ignore[method-assign,assignment]
    try:
        yield asked
    finally:
        loop.call_soon_threadsafe = real  # type: ignore[method-assign]


def writer_for(cache: Cache) -> CacheWriter:
    writer = CacheWriter(cache)
    writer.loop = asyncio.get_running_loop()
    return writer


def turn(writer: CacheWriter, name: str, pitch: float, at: float | None = None) -> None:
    """One turn of the bus loop that read ``name`` (``at``: when it was received)."""
    writer.publish(name, reading(pitch), time.monotonic() if at is None else at)
    writer.flush()


@pytest.mark.anyio
async def test_without_a_prompt_listener_turns_wait_for_a_reader(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Ten turns, no wake-up of the main loop (the lazy period is timed on the bus
    thread), nothing heard yet; the first read applies all ten, in order, before it
    answers; the bus thread then has nothing left to hand over."""
    monkeypatch.setattr(runner, "LAZY_HAND_OVER", 600.0)  # (however slow the machine)
    cache = Cache([("s", 1000)])
    heard: list[float] = []
    cache.subscribe(lambda kind, snap: heard.append(snap.reading.angles.pitch)  # type: ignore[union-attr]
                    if kind is EventKind.READING else None, prompt=False)
    writer = writer_for(cache)
    with wake_ups(asyncio.get_running_loop()) as asked:
        for i in range(10):
            turn(writer, "s", float(i))
        assert asked == []
        assert heard == []
        assert writer.next_at() < math.inf  # (a turn is due when the period ends)
        assert cache.snapshot("s").seq == 10
        assert heard == [float(i) for i in range(10)]
        writer.flush()  # (the bus loop's next turn: nothing waits now)
        assert writer.next_at() == math.inf
        assert asked == []


@pytest.mark.anyio
async def test_the_lazy_period_starts_again_when_a_reader_took_what_waited(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A busy line (a write every turn) whose turns readers keep taking: the period is
    timed from the oldest turn still waiting, not from the first since the last
    hand-over (which would wake the main loop for turns a few ms old)."""
    monkeypatch.setattr(runner, "LAZY_HAND_OVER", 600.0)
    cache = Cache([("s", 1000)])
    writer = writer_for(cache)
    turn(writer, "s", 1.0)
    first = writer.next_at()
    cache.catch_up()  # (a reader: the staleness watch, a PLC's request)
    before = time.monotonic()
    turn(writer, "s", 2.0)
    assert writer.next_at() >= before + 600.0 > first


@pytest.mark.anyio
async def test_without_a_reader_the_bus_thread_hands_over_after_the_lazy_period(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A real bus loop (``Reactor``) with no line: it turns at the writer's time and
    wakes the main loop once; the next turn's writes wait again."""
    monkeypatch.setattr(runner, "LAZY_HAND_OVER", 0.01)
    monkeypatch.setattr(reactor_module, "IDLE_WAIT", 600.0)  # (only the writer's time)
    cache = Cache([("s", 1000)])
    came = asyncio.Event()
    cache.subscribe(lambda kind, snap: came.set(), prompt=False)
    writer = writer_for(cache)
    reactor = Reactor("lazy test")
    reactor.after_each_turn(writer.flush, writer.next_at)
    reactor.start()
    try:
        with wake_ups(asyncio.get_running_loop()) as asked:
            for pitch in (1.0, 2.0):
                came.clear()
                reactor.post(lambda p=pitch: writer.publish(  # type: ignore[misc]
                    "s", reading(p), time.monotonic()))
                await asyncio.wait_for(came.wait(), 10)
                assert cache.snapshot("s").reading.angles.pitch == pitch  # type: ignore[union-attr]
            assert asked == ["_run", "_run"]
    finally:
        reactor.end()
        assert await asyncio.to_thread(reactor.join, 10)
        reactor.close()


@pytest.mark.anyio
async def test_a_prompt_listener_a_claim_or_a_waiter_is_handed_each_turn_at_once() -> None:
    cache = Cache([("s", 1000)])
    writer = writer_for(cache)
    loop = asyncio.get_running_loop()
    with wake_ups(loop) as asked:
        unsubscribe = cache.subscribe(lambda kind, snap: None)  # prompt by default
        assert cache.prompt
        turn(writer, "s", 1.0)
        assert asked == ["_run"]
        unsubscribe()
        assert not cache.prompt
        await asyncio.sleep(0)  # (the hand-over ran)
        release = cache.claim_prompt()  # an SSE stream opened
        turn(writer, "s", 2.0)
        assert asked == ["_run", "_run"]
        release()
        release()  # (twice is harmless)
        assert not cache.prompt
        await asyncio.sleep(0)
        settled: asyncio.Future[None] = loop.create_future()
        writer.hand_urgent(settled.set_result, None)  # a command's answer
        writer.flush()
        assert asked == ["_run", "_run", "_run"]
        await asyncio.wait_for(settled, 10)


@pytest.mark.anyio
async def test_with_a_window_prompt_turns_join_until_its_end_but_a_waiter_never_waits(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """``hand_over_ms``: the first turn goes at once; the turns within the window after
    it wait, the bus loop told to turn at its end (``next_at``), where they go together,
    in order, none lost; a command's answer within the window goes at once."""
    clock = [100.0]
    monkeypatch.setattr(runner, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    cache = Cache([("s", 1000)])
    writer = writer_for(cache)
    writer.window = 0.02
    seen: list[float] = []
    cache.subscribe(lambda kind, snap: seen.append(snap.reading.angles.pitch)
                    if kind is EventKind.READING and snap.reading and snap.reading.angles
                    else None)
    with wake_ups(asyncio.get_running_loop()) as asked:
        turn(writer, "s", 1.0, at=clock[0])
        assert asked == ["_run"]
        await asyncio.sleep(0)  # (the hand-over ran)
        for pitch in (2.0, 3.0):
            clock[0] += 0.005
            turn(writer, "s", pitch, at=clock[0])
        assert asked == ["_run"] and seen == [1.0]
        assert writer.next_at() == pytest.approx(100.02)
        settled: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        writer.hand_urgent(settled.set_result, None)  # a command's answer
        writer.flush()
        assert asked == ["_run", "_run"]
        await asyncio.wait_for(settled, 10)
        assert seen == [1.0, 2.0, 3.0]  # (what waited went with it, first)
        clock[0] += 0.001
        turn(writer, "s", 4.0, at=clock[0])  # (a new window from that hand-over)
        assert asked == ["_run", "_run"]
        clock[0] = writer.next_at()
        writer.flush()  # the bus loop's turn at the window's end
        assert asked == ["_run", "_run", "_run"]
        await asyncio.sleep(0)
        assert seen == [1.0, 2.0, 3.0, 4.0]
        writer.window = 0.0  # (a reload to 0: each turn at once again)
        turn(writer, "s", 5.0, at=clock[0])
        assert asked == ["_run"] * 4


@pytest.mark.anyio
async def test_the_staleness_watch_takes_the_turns_a_window_holds(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A turn held by ``hand_over_ms`` is not left to the window's end by the staleness
    watch: a sensor must not look older than it is (a reader's ``catch_up`` leaves it,
    as with any prompt listener)."""
    clock = [100.0]
    monkeypatch.setattr(runner, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    cache = Cache([("s", 1000)])
    writer = writer_for(cache)
    writer.window = 0.02
    cache.subscribe(lambda kind, snap: None)  # prompt
    turn(writer, "s", 1.0, at=clock[0])
    await asyncio.sleep(0)  # (the hand-over ran)
    clock[0] += 0.005
    turn(writer, "s", 2.0, at=clock[0])  # held: within the window
    def pitch() -> float:
        snap = cache._snapshot("s")
        assert snap.reading is not None and snap.reading.angles is not None
        return snap.reading.angles.pitch

    assert pitch() == 1.0
    cache.check_staleness()
    assert pitch() == 2.0


def test_a_front_end_forgotten_by_a_reload_leaves_no_claim() -> None:
    class FrontEnd:
        def on_event(self, kind: EventKind, snap: Snapshot) -> None:
            pass

    cache, old = Cache([]), FrontEnd()
    cache.subscribe(old.on_event)
    release = cache.claim_prompt()
    cache.forget(old)
    assert cache.prompt  # the claim stays
    release()
    assert not cache.prompt


@pytest.mark.anyio
async def test_a_late_turn_keeps_each_samples_own_time() -> None:
    """Samples received 0.9, 0.6 and 0.3 s ago, applied together now: each timestamp
    and age is its own, not the moment they were applied."""
    cache = Cache([("s", 10_000)])
    times: list[datetime] = []
    cache.subscribe(lambda kind, snap: times.append(snap.timestamp)  # type: ignore[arg-type]
                    if kind is EventKind.READING else None, prompt=False)
    writer = writer_for(cache)
    now = time.monotonic()
    for ago in (0.9, 0.6, 0.3):
        turn(writer, "s", ago, now - ago)
    snap = cache.snapshot("s")
    wall = datetime.now(UTC)
    ages = [(wall - t).total_seconds() for t in times]
    assert [round(a, 1) for a in ages] == [0.9, 0.6, 0.3]
    assert snap.age_ms is not None and 300 <= snap.age_ms < 400


def gateway(**extra: Any) -> Gateway:
    return Gateway(config_from_dict({"buses": [{
        "name": "line", "port": "/dev/null", "protocol": "native",
        "sensors": [{"name": "boom", "series": "AH", "address": 0, "alarms": [
            {"name": "lean", "field": "pitch", "above": 5.0, "on_delay_s": 0.2}]}]}],
        **extra}, env={}))


def pending(gw: Gateway, *samples: tuple[float, float]) -> None:
    """Samples (pitch, received at) a bus handed over and the main loop has not
    applied yet."""
    waiting = list(samples)

    def drain() -> None:
        while waiting:
            pitch, at = waiting.pop(0)
            gw.cache.publish("boom", reading(pitch), at)

    gw.cache.add_source(drain)


@pytest.mark.anyio
async def test_alarm_delays_run_on_the_samples_times_not_when_they_are_applied() -> None:
    """0.25 s of pitch above 5 meets a 0.2 s on-delay, though the three samples are
    applied at the same moment."""
    gw = gateway()
    t0 = time.monotonic() - 1.0
    pending(gw, (6.0, t0), (6.0, t0 + 0.1), (6.0, t0 + 0.25))
    gw.cache.catch_up()
    [lean] = [s for s in gw.alarm_states() if s.name == "lean"]
    assert lean.state.active


@pytest.mark.anyio
async def test_a_modbus_tcp_read_answers_with_what_was_handed_over() -> None:
    """The register images are kept by a listener that is not prompt: a read applies
    the waiting turns first, so it never answers older than the bus handed over."""
    gw = gateway(modbus={"listen": "127.0.0.1:0"})
    assert gw.modbus is not None and not gw.cache.prompt
    pending(gw, (12.5, time.monotonic()))
    answer = gw.modbus.handle(1, READ_FLOATS, writes=False)
    assert isinstance(answer, bytes) and answer[:2] == bytes((0x03, 12))
    assert answer[2:6] == bytes.fromhex("41480000")  # 12.5 as a big-endian f32


@pytest.mark.anyio
async def test_a_rest_request_answers_with_what_was_handed_over() -> None:
    """The history and the alarms are kept by listeners that are not prompt: a request
    applies the waiting turns first."""
    gw = gateway(http={"listen": "127.0.0.1:0"})
    assert gw.http is not None and not gw.cache.prompt
    now = time.monotonic()
    pending(gw, (6.0, now - 0.5), (6.5, now - 0.2))
    assert gw.config.http is not None
    transport = httpx.ASGITransport(app=create_app(gw, gw.config.http))
    async with httpx.AsyncClient(transport=transport, base_url="http://gw") as client:
        alarms = (await client.get("/api/v1/alarms")).json()
        history = (await client.get("/api/v1/sensors/boom/history",
                                    params={"field": "pitch"})).json()
    assert [(a["alarm"], a["active"]) for a in alarms] == \
        [("lean", True), ("communication", False)]
    assert history["fields"]["pitch"]["last"][-1] == 6.5


@pytest.mark.anyio
async def test_opc_ua_reads_and_publishes_what_was_handed_over(tmp_path: Path) -> None:
    """OPC UA is no prompt listener: a client's Read, and a subscription's publish,
    apply the waiting turns first (no staleness watch runs here to do it)."""
    port = free_port()
    gw = gateway(opcua={"listen": f"127.0.0.1:{port}", "allow_none": True,
                        "pki_dir": str(tmp_path / "pki")})
    assert gw.opcua is not None
    await gw.opcua.start()
    try:
        assert not gw.cache.prompt
        async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
            idx = await client.get_namespace_index("urn:imu-gateway")
            pitch = client.get_node(ua.NodeId(f"{gw.config.gateway_id}.Sensors.boom.Angles.pitch",
                                              idx))
            pending(gw, (12.5, time.monotonic()))
            assert await pitch.read_value() == 12.5
            told: list[float] = []

            class Told:
                def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
                    told.append(value)

            subscription = await client.create_subscription(100, Told())
            await subscription.subscribe_data_change([pitch], sampling_interval=0.0,
                                                     queuesize=10)
            await until(lambda: told == [12.5], 10)  # (the initial value)
            pending(gw, (7.25, time.monotonic()), (7.5, time.monotonic()))
            await until(lambda: told[1:] == [7.25, 7.5], 10)
            await subscription.delete()
    finally:
        await gw.opcua.stop()


@pytest.mark.anyio
async def test_an_sse_stream_makes_the_hand_over_prompt_while_it_is_open() -> None:
    gw = gateway(http={"listen": "127.0.0.1:0"})
    hub = StreamHub(gw)
    assert not gw.cache.prompt  # a REST server nobody streams from
    first, second = hub.subscribe(None), hub.subscribe("boom")
    assert gw.cache.prompt
    hub.unsubscribe(first)
    assert gw.cache.prompt
    hub.unsubscribe(second)
    assert not gw.cache.prompt
    hub.subscribe(None)
    hub.close()  # (the server stops: its streams end after)
    assert not gw.cache.prompt


@pytest.mark.anyio
async def test_a_capture_row_keeps_the_wire_time_and_when_the_cache_had_it() -> None:
    """A sample received 0.3 s before the main loop applied it: its capture row's wire
    time is its own, its receive time the moment the cache had it."""
    cache = Cache([("s", 10_000)])
    ring = SensorRing(["pitch", "roll", "yaw"], keep=10)
    cache.subscribe(lambda kind, snap: ring.add(row) if (row := ring.pack(kind, snap))
                    else None, prompt=False)
    writer = writer_for(cache)
    turn(writer, "s", 1.5, time.monotonic() - 0.3)
    cache.catch_up()
    applied = time.time()
    [row] = [r for r in ring.unpack(ring.since(0)) if r.kind == "reading"]
    assert row.wire is not None and abs(row.wire - (applied - 0.3)) < 0.05
    assert abs(row.receive - applied) < 0.05
    assert row.values[0] == 1.5


@pytest.mark.anyio
async def test_with_a_prompt_listener_a_read_takes_the_turn_and_it_is_heard_once() -> None:
    """The hand-over is on its way to the loop, but a read does not wait for it: it
    applies the turn (the listener hears it inside the read), and the hand-over then
    finds nothing left to tell again."""
    cache = Cache([("s", 1000)])
    heard: list[int] = []
    cache.subscribe(lambda kind, snap: heard.append(snap.seq)
                    if kind is EventKind.READING else None)
    writer = writer_for(cache)
    turn(writer, "s", 1.0)
    assert cache.snapshot("s").seq == 1 and heard == [1]
    await asyncio.sleep(0)  # the loop runs the hand-over
    assert heard == [1] and cache.snapshot("s").seq == 1


@pytest.mark.anyio
async def test_a_window_holds_the_listeners_turns_but_no_readers(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """With ``hand_over_ms``, a turn within the window waits for its end to be pushed,
    but a reader (a PLC's request, a REST read) sees it at once; the window's end then
    wakes the loop for nothing, and the listener heard each turn once, in order."""
    clock = [100.0]
    monkeypatch.setattr(runner, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    cache = Cache([("s", 1000)])
    heard: list[int] = []
    cache.subscribe(lambda kind, snap: heard.append(snap.seq)
                    if kind is EventKind.READING else None)
    writer = writer_for(cache)
    writer.window = 0.02
    with wake_ups(asyncio.get_running_loop()) as asked:
        turn(writer, "s", 1.0)
        await asyncio.sleep(0)
        assert asked == ["_run"] and heard == [1]
        clock[0] += 0.005
        turn(writer, "s", 2.0)  # held: within the window
        assert asked == ["_run"] and heard == [1]
        assert cache.snapshot("s").seq == 2 and heard == [1, 2]
        clock[0] = writer.next_at()
        writer.flush()  # the bus loop's turn at the window's end: nothing waits now
        assert asked == ["_run"] and writer.next_at() == math.inf
        clock[0] += 0.005
        turn(writer, "s", 3.0)  # (the window that began at 100.0 is over)
        await asyncio.sleep(0)
        assert asked == ["_run", "_run"] and heard == [1, 2, 3]


def test_a_write_on_the_main_loop_applies_no_turn_in_its_middle() -> None:
    """A write made on the main loop (settings learned, a status tick) tells its own
    event before any waiting turn is applied: a turn applied inside it would have come
    between its state and its event."""
    cache = Cache([("s", 1000)])
    heard: list[EventKind] = []
    cache.subscribe(lambda kind, snap: heard.append(kind), prompt=False)
    waiting = [1.0]

    def drain() -> None:
        while waiting:
            cache.publish("s", reading(waiting.pop()), time.monotonic())

    cache.add_source(drain)
    cache.learn("s", KnownSettings(declination=3.0))
    assert heard == [EventKind.SETTINGS]
    cache.catch_up()
    assert heard[1:] == [EventKind.READING, EventKind.STATUS]


def first_events(chunk: bytes) -> list[tuple[str, int]]:
    """(event, seq) of each event in a stream's chunk."""
    out = []
    for event in chunk.decode().strip().split("\n\n"):
        kind, data = event.split("\n", 1)
        out.append((kind.removeprefix("event: "), json.loads(data.removeprefix("data: "))["seq"]))
    return out


@pytest.mark.anyio
async def test_becoming_prompt_applies_what_waits_first() -> None:
    """An SSE stream opens while turns wait for the lazy timer: they are applied
    before the claim, so readers are not behind after it, and the new stream's first
    events show them; its queue does not get them again."""
    gw = gateway(http={"listen": "127.0.0.1:0"})
    hub = StreamHub(gw)
    writer = writer_for(gw.cache)
    turn(writer, "boom", 7.0)
    sub = hub.subscribe(None)
    assert gw.cache.prompt
    assert gw.cache._entries["boom"].seq == 1  # (applied: no read was needed)
    assert [first_events(chunk) for chunk in sub.events] == [[("reading", 1)]]


@pytest.mark.anyio
async def test_a_stream_opened_within_a_window_gets_each_reading_once(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A stream is open and the window holds a turn; a second stream opens (its first
    events are taken after the held turn is applied), then a reader takes the next
    held turn: each stream gets each reading once, in order, and the window's end adds
    nothing."""
    clock = [100.0]
    monkeypatch.setattr(runner, "time", SimpleNamespace(monotonic=lambda: clock[0]))
    gw = gateway(http={"listen": "127.0.0.1:0"})
    hub = StreamHub(gw)
    writer = writer_for(gw.cache)
    writer.window = 0.02
    one = hub.subscribe(None)
    turn(writer, "boom", 1.0)
    await asyncio.sleep(0)  # (the first turn's hand-over)
    clock[0] += 0.005
    turn(writer, "boom", 2.0)  # held
    two = hub.subscribe(None)
    clock[0] += 0.005
    turn(writer, "boom", 3.0)  # held
    assert gw.cache.snapshot("boom").seq == 3  # a reader takes it
    clock[0] = writer.next_at()
    writer.flush()
    await asyncio.sleep(0)

    def readings(sub: Any) -> list[int]:
        return [seq for chunk in sub.events for kind, seq in first_events(chunk)
                if kind == "reading"]

    assert readings(one) == [1, 2, 3]
    assert readings(two) == [2, 3]


@pytest.mark.anyio
async def test_a_stream_of_a_sensor_gone_leaves_nothing_behind() -> None:
    """A stream of a sensor a reload removed after its route looked: refused as an
    unknown sensor, and it holds no count against the streams' limit, no prompt
    claim and no subscription."""
    gw = gateway(http={"listen": "127.0.0.1:0"})
    hub = StreamHub(gw)
    with pytest.raises(RequestFailed) as gone:
        hub.subscribe("gone")
    assert gone.value.kind is ErrorKind.UNKNOWN_SENSOR
    assert (hub.open, gw.cache.prompt, hub.subscribers) == (0, False, set())


@pytest.mark.anyio
async def test_first_events_show_every_sensor_at_one_moment() -> None:
    """A stream of every sensor opens while the bus hands a reading over at every
    read: its first events are taken after one catch-up, none applied between two of
    them (one applied there, after the first sensor's snapshot and before the stream
    listens, would be lost to it), so it sees every reading once, in order."""
    gw = Gateway(config_from_dict({"buses": [{
        "name": "line", "port": "/dev/null", "protocol": "native",
        "sensors": [{"name": n, "series": "AH", "address": a}
                    for n, a in (("boom", 0), ("arm", 1))]}],
        "http": {"listen": "127.0.0.1:0"}}, env={}))
    hub = StreamHub(gw)
    pitches = iter(range(1, 100))

    def hand_one() -> None:
        gw.cache.publish("boom", reading(float(next(pitches))), time.monotonic())

    gw.cache.add_source(hand_one)
    sub = hub.subscribe(None)
    gw.cache.catch_up()  # (a reader: one more)
    seen = [seq for chunk in sub.events for kind, seq in first_events(chunk)
            if kind == "reading"]
    assert seen == list(range(seen[0], seen[0] + len(seen))) and len(seen) >= 2, seen


@pytest.mark.anyio
async def test_the_buses_stop_with_every_turn_applied(tmp_path: Path) -> None:
    """At the end nobody reads the cache again and the loop ends before a lazy
    timer: the masters' last counters and states are applied by the stop itself."""
    sim = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)
    with simulated([sim]) as line:
        gw = Gateway(config_from_dict({"buses": [{
            "name": "line", "port": line.path, "baudrate": 115200, "protocol": "native",
            "sensors": [{"name": "boom", "series": "AH", "poll_hz": 0}]}]}, env={}))
        stop = asyncio.Event()
        task = asyncio.create_task(gw.run(stop))
        await until(lambda: gw.cache.snapshot("boom").seq >= 3)
        assert not gw.cache.prompt
        stop.set()
        await asyncio.wait_for(task, 30)
    assert not gw.buses.writer._out
    master = gw.masters["line"]
    assert gw.cache._buses["line"].transactions == master.stats.transactions


@pytest.mark.anyio
async def test_an_opc_ua_item_deleted_before_its_value_is_told_gets_nothing(
        caplog: pytest.LogCaptureFixture) -> None:
    """The value is written at once and its monitored items told later (in one task):
    an item deleted in between (by its client, or a reload retiring the node) is not
    told (asyncua's callback would fail on the gone handle; a retired node's item
    would get a value after its BadNodeIdUnknown)."""
    nodeid = ua.NodeId("x", 2)
    node = NodeData(nodeid)
    node.attributes[ua.AttributeIds.Value] = AttributeValue(ua.DataValue())
    told: list[tuple[int, float]] = []

    async def callback(handle: int, value: ua.DataValue) -> None:
        told.append((handle, value.Value.Value))

    callbacks = node.attributes[ua.AttributeIds.Value].datachange_callbacks
    callbacks.update({1: callback, 2: callback})
    writer = DirectWriter(SimpleNamespace(_nodes={nodeid: node}))
    due: list[Any] = []
    writer.write(nodeid, ua.DataValue(ua.Variant(1.5, ua.VariantType.Double)), due)
    del callbacks[1]
    await tell(due)
    assert told == [(2, 1.5)]
    assert not [r for r in caplog.records if r.levelname == "ERROR"]
    assert node.attributes[ua.AttributeIds.Value].value.Value.Value == 1.5


@pytest.mark.anyio
async def test_a_capture_window_has_the_samples_a_lazy_hand_over_still_held(
        tmp_path: Path) -> None:
    """A sample that came in 20 ms before the window's end, in a turn still waiting
    for the lazy hand-over when the window closes: the capture applies the waiting
    turns, and keeps its readings by their wire time (the cache has it only after the
    end).  Its twin at the start: a sample that came in 20 ms before the window began,
    applied only after the trigger, is not in it."""
    gw = gateway(capture={"dir": str(tmp_path), "pre_s": 0.5, "post_s": 0.2})
    assert gw.captures is not None
    await gw.captures.start()
    written: list[Any] = []
    gw.captures.subscribe(written.append)
    waiting: list[float] = []

    def drain() -> None:
        while waiting:
            gw.cache.publish("boom", reading(4.25), waiting.pop())

    gw.cache.add_source(drain)
    capture_id = gw.captures.trigger("manual")
    # received 20 ms before the window began, applied after the trigger
    gw.cache.publish("boom", reading(3.5), time.monotonic() - 0.5 - 0.02)
    # received 20 ms before the window's end, applied (by nothing else reading the
    # cache) only when the window closes
    waiting.append(time.monotonic() + gw.captures.armed(capture_id)["ready_in_s"] - 0.02)
    await until(lambda: bool(written), 10)
    with zipfile.ZipFile(gw.captures.path(capture_id)) as archive:
        rows = list(csv.DictReader(io.StringIO(archive.read("boom.csv").decode())))
    assert [float(r["pitch"]) for r in rows if r["kind"] == "reading"] == [4.25]


def test_a_readings_ts_never_goes_back_for_the_clocks_read_apart(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The monotonic and the wall clock are read one after the other: a thread held
    between the two reads makes a wall time late, and the next sample's would come out
    earlier (a reconnect test beside CPU burners saw ``ts`` go back). It stays; a wall
    clock set back by seconds is followed."""
    mono = [10.0]
    walls = iter([1000.025, 1000.010, 1000.030, 995.040])  # late, on time, on time, set back
    monkeypatch.setattr(time, "time", lambda: next(walls))
    cache = Cache([("s", 10_000)], clock=lambda: mono[0])
    stamps = []
    for step in range(4):
        mono[0] = 10.0 + step * 0.01
        cache.publish("s", reading(1.0), mono[0])
        stamps.append(cache._entries["s"].timestamp.timestamp())  # type: ignore[union-attr]
    assert stamps[:3] == pytest.approx([1000.025, 1000.025, 1000.030])
    assert stamps[3] == pytest.approx(995.040)
