"""The front ends' CPU per sample at a 100 Hz stream: what MQTT (with Home Assistant
discovery), the live stream (SSE), OPC UA and Modbus TCP add to the gateway's CPU,
each with a subscriber, against the gateway with no front end, in the same run.

The gateway runs in this process on 4 AH sensors whose readings are put into its
cache at the rate asked (``--rate``, 100 a second over the sensors by default: one
100 Hz stream), as the bus masters would, without serial lines.  A counter process of
its own (the same machine) subscribes to what the case turns on:

* ``mqtt``: the gateway publishes to a real mosquitto (started here), Home Assistant
  discovery on; one paho subscriber to ``imu/bench/+/state``;
* ``sse``: one client of ``/api/v1/stream`` (every sensor's readings);
* ``opcua``: one asyncua client, one subscription (50 ms, sampling interval 0 and a
  queue of 10 for each item, so that every sample is delivered) to every measured
  value of every sensor (16 a sample: each sample changes 16 monitored values;
  ``--items N``: the first N values of each sensor).  ``--sampling MS`` (> 0): the
  client is a typical SCADA client's (UaExpert's defaults): a 500 ms publishing
  interval, each item sampled every MS ms with a queue of one, so that it gets one
  value an item a ``max(MS, 500)`` ms;
* ``modbus``: Modbus TCP listening, no client (a PLC polls at its own pace; what a
  sample costs there is the register image);
* ``all``: all of them at once; ``none``: no front end (the reference);
* ``paho`` (a reference for MQTT): no front end, and a bare paho client (its network
  thread, as the gateway's) publishing a message of a state's size for each sample,
  subscribed to as ``mqtt``'s: what paho alone costs per message.

Printed per case: the messages delivered against those expected (each sample is one
MQTT state message, one SSE event and 16 OPC UA notifications; with ``--sampling``,
OPC UA's are the sampled ones), the gateway's CPU
(process time ÷ wall time) per sample and the part of it in the kernel (``system``:
system calls, the loopback's TCP work, which on 127.0.0.1 includes the receiving
side's), the times its threads slept and were woken (voluntary context switches) per
sample, and the front ends' share: the case minus ``none`` of the same round.  The
target (issue 29): ``all`` − ``none`` ≤ 0.15 ms.  First, for scale, what a wake-up
of a bare event loop costs on this machine at the same rate.
``--rounds`` repeats every case, in turn; the range over the rounds is printed last.
``--rate 0``: no sample at all: what each front end costs idle, its subscriber
connected (timers, keep-alives, publishing cycles), in ms of CPU a second; at a rate
``r``, that much of each second is in the per-sample figure too, ÷ ``r``.

``--hand-over-ms MS``: the samples come from the bus thread instead, each in a turn of
its own, handed over to the event loop as a line's answers are: at once with 0, or
the turns of ``MS`` together (``hand_over_ms``, docs/deployment.md, "Small boxes").

``--encode``: instead, a notification of one value made and encoded in a loop, by
asyncua's path and by the gateway's (``frontends/opcua/encoding.py``), and a publish of
one sample's notifications, per item.

``--monitored``: instead, a sample's way into the OPC UA values a client monitors at
sampling interval 0 (written, checked, queued; not published), in bursts; ``--items
N``: the first N of the sensor's values.

``--writes``: instead, asyncua's write paths for one value in a loop (process time per
write), without and with a monitored item (a server-side subscription whose publish
never comes in the loop): ``write_attribute_value`` with asyncua's DataValue, with the
gateway's ``Sample`` (its own deep copy), and a node's ``write_value``.

Run: ``.venv/bin/python bench/fanout.py [--seconds 5] [--rounds 3] [--cases none,all]
[--items 16] [--sampling 250]``, or ``--encode``, ``--monitored``, ``--writes``.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NamedTuple

import paho.mqtt.client as paho
from asyncua import Client, ua
from asyncua.ua import ua_binary
from common import FED_SENSORS, fed, fed_config, free_port
from paho.mqtt.enums import CallbackAPIVersion

from imu_gateway.app import GIL_SWITCH_INTERVAL, Gateway
from imu_gateway.cache import EventKind, Snapshot
from imu_gateway.frontends.mqtt.sweep import SWEEP_S
from imu_gateway.frontends.opcua import encoding
from imu_gateway.frontends.opcua.server import Sample
from imu_gateway.frontends.opcua.writes import DirectWriter, tell
from imu_gateway.model import VALUE_GROUPS
from imu_gateway.simulator.motion import Motion

FIELDS = [f"{spec.title}.{name}" for spec in VALUE_GROUPS.values() for name in spec.fields]
FRONT_ENDS = ("mqtt", "sse", "opcua", "modbus")
CASES = ("none", *FRONT_ENDS, "all", "paho")
BARE_TOPIC, BARE_PAYLOAD = "bench/bare/state", b"x" * 420  # (a state message's size)
TARGET_MS = 0.15


@dataclass(frozen=True)
class Ports:
    broker: int
    http: int
    opcua: int
    modbus: int
    items: int  # OPC UA: monitored values per sensor
    sampling: float = 0.0  # OPC UA: the items' sampling interval, ms (0: every sample)
    hand_over_ms: int = -1  # >= 0: fed through the bus thread, with this hand_over_ms


#: ``--sampling``'s client: a SCADA client's publishing interval (ms) and queue size
SCADA_PUBLISHING_MS, SCADA_QUEUE = 500.0, 1


def expected(front_end: str, ports: Ports, rate: float, seconds: float) -> float:
    """Messages a subscriber gets in ``seconds``: one state and one event a sample; a
    notification per monitored value and sample, or, sampled, per monitored value and
    the longer of the sampling and the publishing interval."""
    if rate <= 0:
        return 0.0
    if front_end == "opcua" and ports.sampling > 0:
        every = max(ports.sampling, SCADA_PUBLISHING_MS) / 1000
        return ports.items * FED_SENSORS * seconds / every
    return rate * seconds * {"mqtt": 1, "paho": 1, "sse": 1,
                             "opcua": ports.items}.get(front_end, 0)


def front_ends(case: str) -> tuple[str, ...]:
    return FRONT_ENDS if case == "all" else () if case == "none" else (case,)


class BarePaho:
    """The ``paho`` case: a paho client publishing ``BARE_PAYLOAD`` for each sample."""

    def __init__(self, port: int) -> None:
        self.client = paho.Client(CallbackAPIVersion.VERSION2)
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()

    def on_cache_event(self, kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.READING:
            self.client.publish(BARE_TOPIC, BARE_PAYLOAD, 0, False)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def config_of(case: str, ports: Ports, pki: str) -> dict[str, Any]:
    on = front_ends(case)
    config: dict[str, Any] = {}
    if ports.hand_over_ms >= 0:
        config["hand_over_ms"] = ports.hand_over_ms
    if "mqtt" in on:
        config["mqtt"] = {"url": f"mqtt://127.0.0.1:{ports.broker}",
                          "homeassistant_discovery": True}
    if "sse" in on:
        config["http"] = {"listen": f"127.0.0.1:{ports.http}"}
    if "opcua" in on:
        config["opcua"] = {"listen": f"127.0.0.1:{ports.opcua}", "allow_none": True,
                           "pki_dir": pki}
    if "modbus" in on:
        config["modbus"] = {"listen": f"127.0.0.1:{ports.modbus}"}
    return config


# ------------------------------------------------------------------ the counter process


async def _sse(port: int, counts: dict[str, int]) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET /api/v1/stream HTTP/1.1\r\nHost: bench\r\n\r\n")
    try:
        while line := await reader.readline():
            if line.startswith(b"event: reading"):
                counts["sse"] += 1
    finally:
        writer.close()


async def _opcua(port: int, items: int, sampling: float, counts: dict[str, int],
                 done: asyncio.Event) -> None:
    class Handler:
        def datachange_notification(self, node: object, val: object, data: object) -> None:
            counts["opcua"] += 1

    async with Client(f"opc.tcp://127.0.0.1:{port}/", timeout=30) as client:
        idx = await client.get_namespace_index("urn:imu-gateway")
        nodes = [client.get_node(ua.NodeId(f"bench.Sensors.s{s}.{field}", idx))
                 for s in range(FED_SENSORS) for field in FIELDS[:items]]
        if sampling > 0:  # a SCADA client's
            subscription = await client.create_subscription(SCADA_PUBLISHING_MS, Handler())
            await subscription.subscribe_data_change(nodes, queuesize=SCADA_QUEUE,
                                                     sampling_interval=sampling)
        else:
            subscription = await client.create_subscription(50, Handler())
            # sampling 0 and a queue of 10: every sample delivered (asyncua's client
            # asks 50 ms by default; the default queue, one value, would carry only
            # the newest at each 50 ms publish)
            await subscription.subscribe_data_change(nodes, queuesize=10,
                                                     sampling_interval=0.0)
        await done.wait()
        await subscription.delete()


def _mqtt(port: int, topic: str, counts: dict[str, int]) -> paho.Client:
    client = paho.Client(CallbackAPIVersion.VERSION2)
    client.on_message = lambda *_: counts.__setitem__("mqtt", counts["mqtt"] + 1)
    client.connect("127.0.0.1", port)
    client.subscribe(topic, qos=0)
    client.loop_start()
    return client


def _count(case: str, ports: Ports, warm: float, seconds: float,
           out: multiprocessing.Queue[int]) -> None:
    """Subscribe to what ``case`` turns on; after ``warm`` seconds (the initial values
    are in), count for ``seconds``; put the total."""
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    on = front_ends(case)
    counts = dict.fromkeys(FRONT_ENDS, 0)

    async def main() -> None:
        mqtt = _mqtt(ports.broker, BARE_TOPIC if case == "paho" else "imu/bench/+/state",
                     counts) if {"mqtt", "paho"} & set(on) else None
        done = asyncio.Event()
        tasks = [asyncio.create_task(coro) for coro in (
            _sse(ports.http, counts) if "sse" in on else None,
            _opcua(ports.opcua, ports.items, ports.sampling, counts, done)
            if "opcua" in on else None)
            if coro]
        await asyncio.sleep(warm)
        counts.update(dict.fromkeys(counts, 0))
        await asyncio.sleep(seconds)
        total = sum(counts.values())
        done.set()
        if mqtt is not None:
            mqtt.loop_stop()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        out.put(total)

    asyncio.run(main())


# ------------------------------------------------------------------ the runs


def _ready(case: str, bare: list[BarePaho], port: int) -> Any:
    on = front_ends(case)

    def ready(gw: Gateway) -> bool:
        if case == "paho" and not bare:
            bare.append(BarePaho(port))
            gw.cache.subscribe(bare[0].on_cache_event)
        return ((gw.mqtt is not None and gw.mqtt.connected) or "mqtt" not in on) and \
            all(server is None or server.listening for server in (gw.http, gw.opcua)) and \
            all(b.client.is_connected() for b in bare)
    return ready


class Measured(NamedTuple):
    """One case of one round; per sample, or per second at ``rate`` 0 (idle)."""

    ratio: float  # delivered ÷ expected
    ms: float  # the gateway's ms of CPU
    system: float  # of which in the kernel
    wakeups: float  # times the gateway's threads slept and were woken


async def run_case(case: str, ports: Ports, rate: float, seconds: float,
                   pki: str) -> Measured:
    config = fed_config(**config_of(case, ports, pki))
    bare: list[BarePaho] = []
    # MQTT: measured after the retained sweep of the connect, during which the gateway
    # is subscribed to its own topics and hears its own states (docs/benchmarks.md)
    settle = SWEEP_S + 1.0 if "mqtt" in front_ends(case) else 2.0
    try:
        delivered, cores, system, wakeups = await fed(
            config, rate, seconds, _ready(case, bare, ports.broker), _count,
            (case, ports, settle - 1.0), settle=settle, through_bus=ports.hand_over_ms >= 0)
    finally:
        for client in bare:
            client.close()
    wanted = sum(expected(f, ports, rate, seconds) for f in front_ends(case))
    per = rate if rate > 0 else 1.0
    return Measured(delivered / wanted if wanted else 1.0, 1000 * cores / per,
                    1000 * system / per, wakeups / per)


async def write_paths(pki: str, writes: int = 300) -> None:
    """``--writes``: µs of process time per value written, by each write path."""
    gw = Gateway(fed_config(opcua={"listen": f"127.0.0.1:{free_port()}",
                                   "allow_none": True, "pki_dir": pki}))
    assert gw.opcua is not None
    await gw.opcua.start()
    server = gw.opcua.server
    assert server is not None
    ids = [ua.NodeId(f"bench.Sensors.s0.{field}", gw.opcua.idx) for field in FIELDS]
    now = datetime.now(UTC)

    def value(v: float, kind: Any = ua.DataValue) -> Any:
        # (Double, the nodes' type: a Float is refused, and a refusal is no write)
        return kind(ua.Variant(v, ua.VariantType.Double), SourceTimestamp=now,
                    ServerTimestamp=now)

    direct = DirectWriter(server.iserver.aspace)

    async def write_directly(nodeid: ua.NodeId, v: float) -> None:
        due: list[Any] = []
        direct.write(nodeid, value(v, Sample), due)
        if due:
            await tell(due)

    paths: dict[str, Callable[[Any, float], Awaitable[None]]] = {
        "write_attribute_value, DataValue": lambda i, v: server.write_attribute_value(
            i, value(v)),
        "write_attribute_value, Sample": lambda i, v: server.write_attribute_value(
            i, value(v, Sample)),
        "node.write_value, DataValue": lambda i, v: server.get_node(i).write_value(value(v)),
        "the gateway's (writes.DirectWriter)": write_directly,
    }

    class Quiet:
        def datachange_notification(self, *_: object) -> None: ...

    print(f"{'write path':<36} {'monitored':>9} {'us/write':>8}")
    for monitored in (False, True):
        subscription = None
        if monitored:
            subscription = await server.create_subscription(100_000, Quiet())
            await subscription.subscribe_data_change([server.get_node(i) for i in ids])
        for name, write in paths.items():
            c0 = time.process_time()
            for n in range(writes):
                for nodeid in ids:
                    await write(nodeid, float(n))
            per = (time.process_time() - c0) / (writes * len(ids))
            print(f"{name:<36} {'yes' if monitored else 'no':>9} {per * 1e6:>8.1f}",
                  flush=True)
        if subscription is not None:
            await subscription.delete()
    await gw.opcua.stop()


def encode_paths(rounds: int = 5, count: int = 20_000) -> None:
    """``--encode``: µs of process time per notification of one value, made and encoded
    by asyncua's path and by the gateway's (``opcua/encoding.py``); best of ``rounds``."""
    encoding.install()
    asyncua = encoding.reference()
    now = datetime.now(UTC)
    value = Sample(ua.Variant(1.2345, ua.VariantType.Double), ua.StatusCode(),
                   SourceTimestamp=now, ServerTimestamp=now)

    def made_by_asyncua() -> Any:
        item = ua.MonitoredItemNotification()  # (as its datachange_callback does)
        item.ClientHandle, item.Value = 7, value
        return item

    message = ua.NotificationMessage(SequenceNumber=1, PublishTime=now, NotificationData=[
        ua.DataChangeNotification(MonitoredItems=[made_by_asyncua()] * len(FIELDS))])
    paths: dict[str, Callable[[], object]] = {
        "notification made, asyncua": made_by_asyncua,
        "notification made, the gateway's": lambda: encoding.notification(7, value),
        "DataValue encoded, asyncua": lambda: asyncua(value),
        "DataValue encoded, the gateway's": lambda: ua_binary.struct_to_binary(value),
        f"publish of one sample ({len(FIELDS)} items), per item":
            lambda: ua_binary.struct_to_binary(message),
    }
    print(f"{'path':<48} {'us':>6}")
    for name, path in paths.items():
        best = math.inf
        for _ in range(rounds):
            c0 = time.process_time()
            for _ in range(count):
                path()
            best = min(best, (time.process_time() - c0) / count)
        per_item = len(FIELDS) if "per item" in name else 1
        print(f"{name:<48} {best * 1e6 / per_item:>6.2f}")


async def monitored_path(pki: str, sampling: float = 0.0, items: int = len(FIELDS),
                         rounds: int = 7, samples: int = 300) -> None:
    """``--monitored``: µs of process time per sample put into the cache, with a real
    client subscribed to every value of the sensor at sampling interval 0 (a queue of
    1000, publishing every second: the publish's encoding is left out, ``--encode``
    has it); best of ``rounds`` bursts of ``samples``.  ``sampling`` > 0 (ms): the
    items are sampled so (a queue of one), and the samples come at 100 Hz, paced, so
    that the ticks and publishes that write the newest fall into the time measured."""
    port = free_port()
    gw = Gateway(fed_config(opcua={"listen": f"127.0.0.1:{port}", "allow_none": True,
                                   "pki_dir": pki}))
    stop = asyncio.Event()
    running = asyncio.create_task(gw.run(stop))
    while gw.opcua is None or not gw.opcua.listening:
        await asyncio.sleep(0.05)
    told = [0]

    class Handler:
        def datachange_notification(self, *_: object) -> None:
            told[0] += 1

    async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        idx = await client.get_namespace_index("urn:imu-gateway")
        subscription = await client.create_subscription(1000 if not sampling else 500,
                                                        Handler())
        await subscription.subscribe_data_change(
            [client.get_node(ua.NodeId(f"bench.Sensors.s0.{f}", idx)) for f in FIELDS[:items]],
            queuesize=1 if sampling else 1000, sampling_interval=sampling)
        motion, best = Motion.from_seed(1), math.inf
        loop = asyncio.get_running_loop()
        for r in range(rounds):
            c0, t0 = time.process_time(), loop.time()
            for n in range(samples):
                gw.cache.publish("s0", motion.sample((r * samples + n) / 100))
                await asyncio.sleep(max(0.0, t0 + (n + 1) / 100 - loop.time()) if sampling
                                    else 0)
            best = min(best, (time.process_time() - c0) / samples)
            await asyncio.sleep(1.2)  # (the publish, between two bursts)
    stop.set()
    await running
    how = f"sampled every {sampling:g} ms, 100 Hz paced" if sampling else "sampling 0"
    print(f"a sample with {min(items, len(FIELDS))} monitored values ({how}): "
          f"{best * 1e6:.1f} µs "
          f"(best of {rounds} x {samples}); notifications {told[0]}")


async def bare_wakeup(rate: float, seconds: float = 3.0) -> float:
    """ms of CPU a wake-up of a bare event loop costs, woken by a timer ``rate`` times a
    second and doing nothing else: what this machine charges for a wake-up alone (on a
    VM, the exits and the caches refilled), the floor under every per-sample figure."""
    async def ticks(duration: float) -> int:
        n, loop = 0, asyncio.get_running_loop()
        until = loop.time() + duration
        while loop.time() < until:
            await asyncio.sleep(1 / rate)
            n += 1
        return n

    await ticks(0.5)
    c0 = time.process_time()
    n = await ticks(seconds)
    return 1000 * (time.process_time() - c0) / max(n, 1)


def _broker(folder: Path, port: int) -> subprocess.Popen[bytes]:
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    conf = folder / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\n"
                    "max_queued_messages 100000\n")
    return subprocess.Popen([mosquitto, "-c", str(conf)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def main() -> None:
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    logging.getLogger("imu_gateway").setLevel(logging.ERROR)  # the port it cannot open
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--rate", type=float, default=100.0,
                        help="samples/s, all sensors (0: idle, CPU per second)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--items", type=int, default=len(FIELDS),
                        help="OPC UA: monitored values per sensor")
    parser.add_argument("--hand-over-ms", type=int, default=-1,
                        help="feed the samples through the bus thread, with this "
                        "hand_over_ms (default: into the cache on the event loop)")
    parser.add_argument("--sampling", type=float, default=0.0,
                        help="OPC UA: the items' sampling interval, ms (> 0: a SCADA "
                        "client's subscription, see above)")
    parser.add_argument("--cases", default=",".join(CASES),
                        help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument("--writes", action="store_true",
                        help="asyncua's write paths in a loop instead (see above)")
    parser.add_argument("--encode", action="store_true",
                        help="a notification's making and encoding in a loop instead")
    parser.add_argument("--monitored", action="store_true",
                        help="a sample's way into monitored OPC UA values instead")
    args = parser.parse_args()
    if args.encode:
        encode_paths()
        return
    if args.monitored:
        with tempfile.TemporaryDirectory() as pki:
            asyncio.run(monitored_path(pki, args.sampling, args.items))
        return
    if args.writes:
        with tempfile.TemporaryDirectory() as pki:
            asyncio.run(write_paths(pki))
        return
    cases = args.cases.split(",")
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)  # as `imu-gateway run` does
    ports = Ports(free_port(), free_port(), free_port(), free_port(), args.items,
                  args.sampling, args.hand_over_ms)
    shares: dict[str, list[float]] = {case: [] for case in cases}
    unit = "gw ms/sample" if args.rate > 0 else "gw ms/s"  # (idle: CPU per second)
    with tempfile.TemporaryDirectory() as folder:
        broker = _broker(Path(folder), ports.broker)
        try:
            time.sleep(0.5)
            print(f"{FED_SENSORS} AH sensors, {args.rate:g} samples/s in all, "
                  f"{args.seconds:g} s per case, {args.rounds} rounds, {os.cpu_count()} CPUs; "
                  f"OPC UA: {args.items} monitored values per sensor, sampled "
                  f"{f'every {args.sampling:g} ms' if args.sampling > 0 else 'every sample'}"
                  + (f"; through the bus thread, hand_over_ms {args.hand_over_ms}"
                     if args.hand_over_ms >= 0 else ""))
            if args.rate > 0:
                print(f"a bare event loop woken {args.rate:g} times a second: "
                      f"{asyncio.run(bare_wakeup(args.rate)):.3f} ms of CPU a wake-up")
            print(f"{'round':>5} {'case':>6} {'delivered':>9} {unit:>12} {'system':>7} "
                  f"{'wakeups':>7} {'- none':>7} {'system':>7} {'wakeups':>7}")
            for n in range(args.rounds):
                reference: Measured | None = None
                for case in cases:
                    m = asyncio.run(run_case(case, ports, args.rate, args.seconds, folder))
                    if case == "none":
                        reference = m
                    extra = ""
                    if reference is not None and case != "none":
                        shares[case].append(m.ms - reference.ms)
                        extra = (f"{m.ms - reference.ms:7.3f} "
                                 f"{m.system - reference.system:7.3f} "
                                 f"{m.wakeups - reference.wakeups:7.2f}")
                    print(f"{n + 1:>5} {case:>6} {m.ratio:>9.2f} {m.ms:>12.3f} "
                          f"{m.system:>7.3f} {m.wakeups:>7.2f} {extra}", flush=True)
        finally:
            broker.terminate()
            broker.wait(10)
    print(f"\nfront ends' CPU {'per sample' if args.rate > 0 else 'per second, idle'} "
          f"(case - none), ms, over {args.rounds} rounds:")
    for case, values in shares.items():
        if values:
            verdict = "" if case != "all" or args.rate <= 0 else \
                ("  target met" if max(values) <= TARGET_MS else
                 f"  over the {TARGET_MS} ms target")
            print(f"{case:>6} {min(values):.3f}-{max(values):.3f}{verdict}")


if __name__ == "__main__":
    main()
