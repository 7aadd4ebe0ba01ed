"""The live stream's cost per event (issue 29; docs/benchmarks.md, "CPU per sample in
the front ends"): the events queued when a stream wakes go in one HTTP chunk, each
whole and in order; a waiting stream arms no timer per event, and still sends its
keep-alive when idle; a client that goes away ends its stream though no event comes.

Through a real HTTP server and a raw socket (the chunks are what is tested), with the
readings put into the gateway's cache by the test, in the gateway's own loop."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import pytest
from support.harness import running, until
from support.streams import hub_stream

from imu_gateway.app import Gateway
from imu_gateway.config import config_from_dict
from imu_gateway.frontends.rest import StreamHub, streams
from imu_gateway.simulator.motion import Motion

API = "/api/v1"
CONFIG: dict[str, Any] = {
    "gateway_id": "chunks",
    # A line that does not open: the test is the only source of readings.
    "buses": [{"name": "a", "port": "/dev/null-chunks", "protocol": "native",
               "sensors": [{"name": "s", "series": "AH"}]}],
    "http": {"listen": "127.0.0.1:0"}}


async def _chunks(reader: asyncio.StreamReader) -> AsyncIterator[bytes]:
    """The payload of each HTTP chunk of a chunked answer, as the chunks came."""
    while True:
        size = int((await reader.readuntil(b"\r\n")).strip(), 16)
        payload = await reader.readexactly(size + 2)
        assert payload.endswith(b"\r\n")
        if size == 0:
            return
        yield payload[:-2]


async def _open_stream(gateway: Gateway) -> tuple[asyncio.StreamReader,
                                                  asyncio.StreamWriter]:
    assert gateway.http is not None
    reader, writer = await asyncio.open_connection("127.0.0.1", gateway.http.port)
    writer.write(f"GET {API}/sensors/s/stream HTTP/1.1\r\nHost: t\r\n\r\n".encode())
    head = await reader.readuntil(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 200") and b"transfer-encoding: chunked" in head
    return reader, writer


@pytest.mark.anyio
async def test_events_queued_when_the_stream_wakes_go_whole_and_in_order_in_one_chunk(
        ) -> None:
    async with running(CONFIG) as gateway:
        reader, writer = await _open_stream(gateway)
        try:
            chunks = _chunks(reader)
            assert (await anext(chunks)).startswith(b"event: status\n")  # where s stands
            motion = Motion.from_seed(2)
            # Published in one turn of the gateway's loop: all queued when the stream
            # wakes, so all due at once.
            seqs = [gateway.cache.publish("s", motion.sample(n / 100)) for n in range(5)]
            chunk = await asyncio.wait_for(anext(chunks), 10)
            events = chunk.split(b"\n\n")
            assert events[-1] == b""  # the chunk ends where an event ends
            readings = [json.loads(event.split(b"\ndata: ", 1)[1])["seq"]
                        for event in events[:-1] if event.startswith(b"event: reading\n")]
            assert readings == seqs  # every one, whole, in order, in this one chunk
        finally:
            writer.close()


@pytest.mark.anyio
async def test_a_waiting_stream_arms_no_timer_per_event(monkeypatch: pytest.MonkeyPatch
                                                        ) -> None:
    gateway = Gateway(config_from_dict(CONFIG, env={}))
    hub = StreamHub(gateway)
    motion = Motion.from_seed(4)
    gateway.cache.publish("s", motion.sample(0.0))  # (s online: then a reading an event)
    stream = hub_stream(hub, "s")
    await anext(stream)  # subscribed
    loop = asyncio.get_running_loop()
    armed: list[float] = []
    call_at = loop.call_at

    def counted(when: float, *args: Any, **kwargs: Any) -> asyncio.TimerHandle:
        armed.append(when)
        return call_at(when, *args, **kwargs)

    monkeypatch.setattr(loop, "call_at", counted)
    for n in range(1, 21):
        waiting = asyncio.ensure_future(anext(stream))
        await asyncio.sleep(0)  # the stream waits
        assert not waiting.done()
        seq = gateway.cache.publish("s", motion.sample(n / 100))
        assert b'"seq":%d,' % seq in await waiting  # (due: no deadline needed)
    assert armed == []  # (an asyncio.timeout around each wait arms and cancels one)
    hub.close()
    await stream.aclose()
    assert hub.open == 0


@pytest.mark.anyio
async def test_an_idle_stream_sends_a_keep_alive_a_period_after_its_last_chunk(
        monkeypatch: pytest.MonkeyPatch) -> None:
    period = 0.3
    monkeypatch.setattr(streams, "KEEPALIVE_S", period)
    gateway = Gateway(config_from_dict(CONFIG, env={}))
    hub = StreamHub(gateway)
    motion = Motion.from_seed(1)
    gateway.cache.publish("s", motion.sample(0.0))  # (s online: the next is a reading only)
    stream = hub_stream(hub, "s")
    loop = asyncio.get_running_loop()
    await anext(stream)
    for n in range(3):
        sent = loop.time()
        if n == 1:  # an event restarts the idle period
            gateway.cache.publish("s", motion.sample(0.01))
            assert b"event: reading" in await asyncio.wait_for(anext(stream), 10)
            sent = loop.time()
        assert await asyncio.wait_for(anext(stream), 10) == b": keep-alive\n\n"
        assert loop.time() - sent >= period - 0.01
    hub.close()
    assert [chunk async for chunk in stream] == []
    assert hub.open == 0


@pytest.mark.anyio
async def test_a_client_that_goes_away_ends_its_idle_stream() -> None:
    async with running(CONFIG) as gateway:
        assert gateway.http is not None and gateway.http.hub is not None
        hub = gateway.http.hub
        reader, writer = await _open_stream(gateway)
        await anext(_chunks(reader))
        assert hub.open == 1 and len(hub.subscribers) == 1
        writer.close()  # no event comes: only the disconnect can end the stream
        await until(lambda: hub.open == 0 and not hub.subscribers, timeout=30)
        await until(lambda: gateway.http is not None
                    and gateway.http.stats()["clients"] == 0, timeout=30)
