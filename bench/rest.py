"""REST: readings/s and latency against a bare FastAPI app, and how many live-stream
(SSE) subscribers one gateway serves.

Processes besides this one: the sensor simulator, the gateway (``imu-gateway run``)
with one AH sensor at 115200 baud, and a bare FastAPI app on uvicorn that returns a
constant reading JSON of the same shape (the ceiling: it does nothing but answer).
This process is the load: raw asyncio HTTP/1.1 keep-alive clients, the same code for
both servers.

1. ``GET /api/v1/sensors/boom/reading`` with 1, 10 and 50 concurrent clients:
   readings/s, p50/p99, gateway/bare.
2. SSE: the sensor polled at 20 Hz, N subscribers of ``/api/v1/sensors/boom/stream``
   (N = 10, 50, 100, 200, 300, 400, 600, 800).  Latency: from the reading's ``ts`` (when the
   gateway received it) to its arrival at the subscriber.  The run stops at the first
   N whose p99 passes 100 ms.

Run: ``.venv/bin/python bench/rest.py [--seconds 5]``
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import sys
import time
from datetime import datetime

from common import free_port, processes

BARE_APP = """
import sys, uvicorn
from fastapi import FastAPI
from fastapi.responses import Response
BODY = (b'{"sensor":"boom","ts":"2026-11-22T03:40:00.123Z","seq":1234,"status":"ok",'
        b'"angles":{"pitch":-13.15,"roll":25.58,"yaw":251.87},'
        b'"accel":{"x":-0.1807,"y":-0.2816,"z":1.0265},"gyro":{"x":-6.48,"y":124.13,"z":3.88},'
        b'"mag":{"x":0.15962,"y":0.16391,"z":-0.41458},'
        b'"quaternion":{"q0":-0.228375,"q1":-0.183349,"q2":-0.165578,"q3":0.939914}}')
app = FastAPI()
@app.get("/api/v1/sensors/boom/reading")
async def reading() -> Response:
    return Response(BODY, media_type="application/json")
uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), log_level="warning",
            access_log=False)
"""

READING = "/api/v1/sensors/boom/reading"
STREAM = "/api/v1/sensors/boom/stream"
SSE_STEPS = (10, 50, 100, 200, 300, 400, 600, 800)
SSE_LIMIT_MS = 100.0


async def wait_for(port: int, path: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(f"GET {path} HTTP/1.1\r\nHost: b\r\n\r\n".encode())
            status = await reader.readline()
            writer.close()
            if b" 200 " in status:
                return
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise SystemExit(f"no 200 from port {port}{path}")
        await asyncio.sleep(0.2)


async def get_loop(port: int, deadline: float, latencies: list[float]) -> int:
    """One keep-alive client reading the same resource until the deadline."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    request = f"GET {READING} HTTP/1.1\r\nHost: bench\r\n\r\n".encode()
    done = 0
    while (start := time.perf_counter()) < deadline:
        writer.write(request)
        status = await reader.readline()
        length = 0
        while (line := await reader.readline()) not in (b"\r\n", b""):
            if line[:15].lower() == b"content-length:":
                length = int(line[15:])
        await reader.readexactly(length)
        if b" 200 " not in status:
            raise SystemExit(f"answer {status!r}")
        latencies.append(time.perf_counter() - start)
        done += 1
    writer.close()
    return done


async def load(port: int, clients: int, seconds: float) -> tuple[float, float, float]:
    latencies: list[float] = []
    started = time.perf_counter()
    counts = await asyncio.gather(*(get_loop(port, started + seconds, latencies)
                                    for _ in range(clients)))
    elapsed = time.perf_counter() - started
    latencies.sort()
    return (sum(counts) / elapsed, statistics.median(latencies) * 1000,
            latencies[int(len(latencies) * 0.99) - 1] * 1000)


async def subscriber(port: int, until: float, latencies: list[float], ready: list[int]) -> None:
    """One SSE client: the latency of every reading event, from its ``ts``."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"GET {STREAM} HTTP/1.1\r\nHost: bench\r\n\r\n".encode())
    ready.append(1)
    reading = False
    try:
        while time.time() < until:
            line = await asyncio.wait_for(reader.readline(), max(0.1, until - time.time()))
            if line.startswith(b"event:"):
                reading = line.startswith(b"event: reading")
            elif reading and line.startswith(b"data:"):
                at = time.time()
                start = line.find(b'"ts":"') + 6
                ts = datetime.fromisoformat(line[start:start + 24].decode()).timestamp()
                latencies.append(at - ts)
    except TimeoutError:
        pass
    finally:
        writer.close()


async def sse_step(port: int, subscribers: int, seconds: float) -> tuple[int, float, float, float]:
    """N subscribers for ``seconds`` after they are all connected; events/s per
    subscriber, p50, p99 (ms)."""
    latencies: list[float] = []
    ready: list[int] = []
    settle = 1.0 + subscribers / 400
    until = time.time() + settle + seconds
    tasks = [asyncio.create_task(subscriber(port, until, latencies, ready))
             for _ in range(subscribers)]
    await asyncio.sleep(settle)
    latencies.clear()  # measure once everyone is in
    await asyncio.gather(*tasks)
    latencies.sort()
    if not latencies:
        return subscribers, 0.0, float("nan"), float("nan")
    per_client = len(latencies) / subscribers / seconds
    return (subscribers, per_client, statistics.median(latencies) * 1000,
            latencies[int(len(latencies) * 0.99) - 1] * 1000)


async def measure(gateway: int, bare: int, seconds: float) -> None:
    await wait_for(gateway, READING)
    await wait_for(bare, READING)
    print(f"{'clients':>7} {'server':>8} {'readings/s':>10} {'p50 ms':>7} {'p99 ms':>7} "
          f"{'gateway/bare':>12}")
    for clients in (1, 10, 50):
        bare_result = await load(bare, clients, seconds)
        ours = await load(gateway, clients, seconds)
        for name, (rate, p50, p99) in (("bare", bare_result), ("gateway", ours)):
            ratio = f"{ours[0] / bare_result[0]:12.2f}" if name == "gateway" else ""
            print(f"{clients:7} {name:>8} {rate:10.0f} {p50:7.2f} {p99:7.2f} {ratio}",
                  flush=True)
    print(f"\nSSE, sensor polled at 20 Hz: {'subscribers':>11} {'events/s each':>13} "
          f"{'p50 ms':>7} {'p99 ms':>7}")
    for n in SSE_STEPS:
        count, per_client, p50, p99 = await sse_step(gateway, n, seconds)
        print(f"{'':28} {count:11} {per_client:13.1f} {p50:7.1f} {p99:7.1f}", flush=True)
        if not p99 <= SSE_LIMIT_MS:
            print(f"p99 passed {SSE_LIMIT_MS:.0f} ms at {n} subscribers")
            break
    else:
        print(f"p99 stayed under {SSE_LIMIT_MS:.0f} ms up to {SSE_STEPS[-1]} subscribers")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    args = parser.parse_args()
    gateway_port, bare_port = free_port(), free_port()
    bare = [sys.executable, "-c", BARE_APP, str(bare_port)]
    interfaces = f"http:\n  listen: 127.0.0.1:{gateway_port}"
    with processes("{name: boom, series: AH, poll_hz: 20}", interfaces, bare):
        print(f"REST, {args.seconds:g} s per run, {os.cpu_count()} CPUs; load generator: "
              "raw asyncio HTTP/1.1 keep-alive clients in one process")
        asyncio.run(measure(gateway_port, bare_port, args.seconds))


if __name__ == "__main__":
    main()
