"""MQTT: latency from a sample's last byte on the wire to the message at a subscriber,
and the sustained message rate of a fast streaming sensor.

One native AH sensor at 460800 baud streams its own auto-output at 500 Hz
(``stream_hz: 500``).  Three processes, as in a plant:

* the simulator, which notes the moment each streamed frame's last byte leaves the
  simulated wire (its model time, on the machine's clock);
* the gateway (this process), which publishes every reading to a real mosquitto;
* ``mosquitto_sub``, an independent subscriber that stamps each message on arrival
  (``-F '%U %p'``).

A message is matched to its frame by the sample's values (the same values cannot
come twice from the moving simulated sensor; a value set that does is left out).

The reference in the same run: a bare paho publisher sending the same number of
messages per second straight to the broker, stamped just before ``publish()``.
Its latency is what the broker and the subscriber alone cost.

Run: ``.venv/bin/python bench/mqtt.py [--seconds 10] [--rate 500] [--baud 460800]
[--hand-over-ms 20]``
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from support.broker import Mosquitto
from support.harness import fields_of

from imu_gateway.app import GIL_SWITCH_INTERVAL, Gateway
from imu_gateway.config import config_from_dict
from imu_gateway.model import Series, WireProtocol
from imu_gateway.normalise import field_values, to_reading
from imu_gateway.protocol import native
from imu_gateway.simulator import make_sensor
from imu_gateway.simulator.bus import PtyBus
from imu_gateway.simulator.motion import Motion

TOPIC = "imu/bench/boom/state"
WARM_UP = 1.0  # seconds left out at the start


def key_of(values: dict[str, float]) -> tuple[float, ...]:
    return tuple(values[name] for name in sorted(values))


# ------------------------------------------------------------------ the simulator


def simulator(baud: int, pipe: Connection) -> None:
    """The simulator process: serve one AH sensor; when told to stop, send back the
    wall-clock end time and bytes of every frame it streamed."""
    sent: list[tuple[float, bytes]] = []

    def note(end: float, frame: bytes, solicited: bool) -> None:
        if not solicited:
            sent.append((end, frame))

    bus = PtyBus([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=baud,
                              source=Motion.from_seed(11))], on_sent=note)

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        threading.Thread(target=lambda: (pipe.recv(), loop.call_soon_threadsafe(stop.set)),
                         daemon=True).start()
        await bus.serve(stop, on_ready=lambda: pipe.send(bus.path))

    asyncio.run(main())
    # The loop's clock is time.monotonic(); the subscriber stamps in wall-clock time.
    offset = time.time() - time.monotonic()
    pipe.send([(end + offset, frame) for end, frame in sent])


def frame_times(sent: list[tuple[float, bytes]]) -> dict[tuple[float, ...], float]:
    """Each streamed sample's values -> when its last byte was on the wire."""
    times: dict[tuple[float, ...], float] = {}
    seen: Counter[tuple[float, ...]] = Counter()
    for end, frame in sent:
        reading = to_reading(native.decode(frame, Series.AH).values, Series.AH)
        if reading is None:
            continue
        key = key_of(field_values(reading))
        seen[key] += 1
        times[key] = end
    return {k: t for k, t in times.items() if seen[k] == 1}


# ------------------------------------------------------------------ the subscriber


def subscribe(broker: Mosquitto, topic: str, seconds: float, out: Path) -> subprocess.Popen[bytes]:
    """mosquitto_sub, stamping each message on arrival; it exits by itself."""
    with out.open("wb") as sink:
        proc = subprocess.Popen(
            ["mosquitto_sub", "-h", "127.0.0.1", "-p", str(broker.port), "-t", topic,
             "-F", "%U %p", "-W", str(int(seconds) + 1)],
            stdout=sink, stderr=subprocess.DEVNULL)
    time.sleep(0.3)  # subscribed
    return proc


def arrivals(out: Path) -> list[tuple[float, str]]:
    rows = []
    for line in out.read_text().splitlines():
        stamp, _, payload = line.partition(" ")
        if payload:
            rows.append((float(stamp), payload))
    return rows


def percentile(values: list[float], p: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(p / 100 * len(ordered)))]


# ------------------------------------------------------------------ the runs


async def run_gateway(broker: Mosquitto, port: str, baud: int, rate: float,
                      seconds: float, hand_over_ms: int = 0) -> dict[str, Any]:
    config = config_from_dict({
        "gateway_id": "bench", "hand_over_ms": hand_over_ms,
        "buses": [{"name": "line", "port": port, "baudrate": baud, "protocol": "native",
                   "sensors": [{"name": "boom", "series": "AH", "stream_hz": rate}]}],
        "mqtt": {"url": broker.url, "qos": 0, "retain": False},
    }, env={})
    gateway = Gateway(config)
    stop = asyncio.Event()
    task = asyncio.create_task(gateway.run(stop))
    while not gateway.cache.snapshot("boom").streaming:
        await asyncio.sleep(0.05)
    await asyncio.sleep(WARM_UP)
    assert gateway.mqtt is not None
    seq0, published0 = gateway.cache.snapshot("boom").seq, gateway.mqtt.counters.published
    started = time.monotonic()
    await asyncio.sleep(seconds)
    elapsed = time.monotonic() - started
    result = {
        "samples_per_s": (gateway.cache.snapshot("boom").seq - seq0) / elapsed,
        "published_per_s": (gateway.mqtt.counters.published - published0) / elapsed,
        "dropped": gateway.mqtt.outbox.dropped,
        "window": (time.time() - elapsed, time.time()),
    }
    stop.set()
    await task
    return result


def bare_publisher(broker: Mosquitto, rate: float, seconds: float) -> None:
    """The reference: paho alone, publishing stamped messages at ``rate``."""
    client = paho.Client(CallbackAPIVersion.VERSION2)
    client.connect("127.0.0.1", broker.port)
    client.loop_start()
    period = 1.0 / rate
    next_at = time.monotonic()
    end = next_at + seconds
    while next_at < end:
        client.publish("bench/bare", json.dumps({"t": time.time(), "pad": "x" * 250}))
        next_at += period
        time.sleep(max(0.0, next_at - time.monotonic()))
    client.disconnect()
    client.loop_stop()


def latency_line(name: str, latencies: list[float], per_s: float, extra: str = "") -> str:
    ms = [x * 1000 for x in latencies]
    return (f"{name:<22} {len(ms):>7} {per_s:>9.1f} {statistics.median(ms):>8.2f} "
            f"{percentile(ms, 99):>8.2f} {max(ms):>8.2f}  {extra}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--rate", type=float, default=500.0, help="the sensor's stream_hz")
    parser.add_argument("--baud", type=int, default=460800)
    parser.add_argument("--hand-over-ms", type=int, default=0,
                        help="the gateway's hand_over_ms (docs/deployment.md)")
    args = parser.parse_args()
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)  # as `imu-gateway run` does

    with tempfile.TemporaryDirectory() as tmp, Mosquitto(Path(tmp)) as broker:
        folder = Path(tmp)
        ours, theirs = multiprocessing.get_context("spawn").Pipe()
        sim = multiprocessing.get_context("spawn").Process(target=simulator,
                                                           args=(args.baud, theirs))
        sim.start()
        port = ours.recv()

        sub = subscribe(broker, TOPIC, args.seconds + WARM_UP + 5, folder / "gateway.txt")
        result = asyncio.run(run_gateway(broker, port, args.baud, args.rate, args.seconds,
                                         args.hand_over_ms))
        ours.send("stop")
        sent = frame_times(ours.recv())
        sim.join(10)
        sub.wait(30)

        begin, end = result["window"]
        latencies = []
        received = 0
        for stamp, payload in arrivals(folder / "gateway.txt"):
            body = json.loads(payload)
            values = fields_of(body)
            if not begin <= stamp <= end:
                continue
            received += 1
            wire_end = sent.get(key_of(values))
            if wire_end is not None:
                latencies.append(stamp - wire_end)

        ref_out = folder / "bare.txt"
        ref_sub = subscribe(broker, "bench/bare", args.seconds + 3, ref_out)
        bare_publisher(broker, args.rate, args.seconds)
        ref_sub.wait(30)
        reference = [stamp - json.loads(p)["t"] for stamp, p in arrivals(ref_out)]

    span = end - begin
    print(f"native AH at {args.baud} baud streaming at {args.rate:g} Hz; "
          f"{args.seconds:g} s measured after {WARM_UP:g} s warm-up")
    print(f"sensor samples in the gateway: {result['samples_per_s']:.1f}/s; "
          f"state messages published: {result['published_per_s']:.1f}/s; "
          f"dropped: {result['dropped']}")
    print(f"{'path':<22} {'matched':>7} {'msgs/s':>9} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    print(latency_line("wire -> gateway -> sub", latencies, received / span,
                       f"(received {received}, matched {len(latencies)})"))
    print(latency_line("bare paho -> sub", reference, len(reference) / args.seconds))



if __name__ == "__main__":
    main()
