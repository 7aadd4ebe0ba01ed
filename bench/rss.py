"""What the gateway's memory keeps after an attack: the real process, its VmRSS.

    .venv/bin/python bench/rss.py [--trickle 400] [--garbage 57000] [--trace] [--json F]

Starts two simulated lines (a native AH and VG polled at 10 Hz; a Modbus AH streaming
at 20 Hz), mosquitto, and ``python -m imu_gateway run`` with every front end on (Modbus
TCP, MQTT 5 with Home Assistant discovery, HTTP, OPC UA).  Then, one after the other,
with a quiet settle after each:

1. **trickle**: ``--trickle`` connections (half HTTP, half Modbus TCP) from 127.0.0.2,
   each sending its request one byte every 2 s and never the last (closed ones come
   back a second later), for ``--hold`` seconds;
2. **garbage**: ``--garbage`` REST requests from 20 connections at once: unknown
   paths, bad methods, bad tokens, bodies that are not JSON, request lines that are not
   HTTP (``docs/reliability.md`` has the mix and the figures).

VmRSS (``/proc/PID/status``) is sampled at the start, at the end of each attack, and
after each settle.  With ``--trace`` the gateway runs under ``tracemalloc`` (slower,
and more memory of its own): the Python-level total is sampled at the same moments,
and the biggest growths by line are printed.  At the end the gateway is asked to
``malloc_trim(0)``: what RSS then gives back was free memory the allocator held.

The gateway is started through this file (``--child``), which adds a SIGUSR1 handler
that writes those figures to a file: the gateway's own code is unchanged.

    .venv/bin/python bench/rss.py --start 5 [--hold 30]

**Start-up** instead (docs/deployment.md, "Small boxes"): the plain ``python -m
imu_gateway run``, ``--start`` times bus-only and ``--start`` times with every front end
(Modbus TCP, MQTT with Home Assistant discovery and Sparkplug B on a real mosquitto,
HTTP, OPC UA), alternately: the time from the process's start to its first reading (the
log's first "online"), VmRSS then, and, with every front end, VmRSS after ``--hold``
seconds of two clients of each (Modbus TCP pollers, a REST poller and a live stream,
MQTT subscribers, OPC UA subscriptions).  The reference, as often: a bare Python
process that imports every module of other packages the gateway's code imports
(asyncua, FastAPI, paho, pymodbus, pydantic, …, found in its sources), its VmRSS.
"""

from __future__ import annotations

import argparse
import ast
import asyncio
import contextlib
import ctypes
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
import tracemalloc
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from hostile import (
    PARTIAL_HEADERS,
    PARTIAL_MBAP,
    HttpPoller,
    ModbusPoller,
    SseReader,
    Swarm,
    trickle,
)
from support.broker import Mosquitto, Recorder

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated

FAST = 115200
TOKEN = "rss-token"
HOST = "127.0.0.1"


# ------------------------------------------------------------------ the gateway's side


def child(config: str, report: str, trace: bool) -> int:
    """The gateway, with a SIGUSR1 handler that writes its memory figures to
    ``report`` (SIGUSR2: ``malloc_trim(0)`` first)."""
    if trace:
        tracemalloc.start(1)
    baseline: list[tracemalloc.Snapshot] = []

    def dump(trim: bool) -> None:
        if trim:
            ctypes.CDLL("libc.so.6").malloc_trim(0)
        out: dict[str, Any] = {"rss_mb": rss_mb(os.getpid()),
                               "threads": len(os.listdir("/proc/self/task"))}
        if trace:
            current, peak = tracemalloc.get_traced_memory()
            out.update(traced_mb=current / 2**20, traced_peak_mb=peak / 2**20)
            snap = tracemalloc.take_snapshot().filter_traces(
                [tracemalloc.Filter(False, tracemalloc.__file__)])
            if not baseline:
                baseline.append(snap)
            out["top"] = [str(stat) for stat in
                          snap.compare_to(baseline[0], "lineno")[:12]]
        Path(report).write_text(json.dumps(out))

    signal.signal(signal.SIGUSR1, lambda *_: dump(False))
    signal.signal(signal.SIGUSR2, lambda *_: dump(True))
    from imu_gateway.tools.cli import main
    return main(["run", "-c", config])


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


class Gateway:
    def __init__(self, folder: Path, config: str, trace: bool, env: dict[str, str]) -> None:
        self.report = folder / "memory.json"
        path = folder / "gateway.yaml"
        path.write_text(config)
        self.log = (folder / "gateway.log").open("wb")
        self.process = subprocess.Popen(
            [sys.executable, __file__, "--child", str(path), str(self.report),
             *(["--trace"] if trace else [])],
            stdout=self.log, stderr=subprocess.STDOUT, env={**os.environ, **env})

    async def figures(self, trim: bool = False) -> dict[str, Any]:
        self.report.unlink(missing_ok=True)
        self.process.send_signal(signal.SIGUSR2 if trim else signal.SIGUSR1)
        for _ in range(4000):  # (a snapshot of a traced heap takes a while)
            with contextlib.suppress(FileNotFoundError, json.JSONDecodeError):
                found: dict[str, Any] = json.loads(self.report.read_text())
                return found
            await asyncio.sleep(0.05)
        raise RuntimeError("the gateway wrote no figures")

    def stop(self) -> None:
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(20)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def config_yaml(lines: dict[str, str], ports: dict[str, int], broker: Mosquitto,
                pki: Path) -> str:
    return f"""gateway_id: rss
buses:
  - name: a
    port: {lines['a']}
    baudrate: {FAST}
    protocol: native
    sensors:
      - {{name: a1, series: AH, address: 0, poll_hz: 10}}
      - {{name: a2, series: VG, address: 1, poll_hz: 10}}
  - name: b
    port: {lines['b']}
    baudrate: {FAST}
    protocol: modbus
    sensors:
      - {{name: b1, series: AH, address: 1, stream_hz: 20}}
modbus: {{listen: '{HOST}:{ports['modbus']}', allow_writes: true}}
mqtt: {{url: '{broker.url}', protocol: 5, allow_commands: true,
       homeassistant_discovery: true}}
http: {{listen: '{HOST}:{ports['http']}', token: {TOKEN}, allow_commands: true}}
opcua: {{listen: '{HOST}:{ports['opcua']}', allow_none: true, pki_dir: '{pki}'}}
"""


# ------------------------------------------------------------------ the attacks


def garbage_request(rng: random.Random) -> bytes:
    """One request of the mix: most are answered (404, 401, 405, 422), some are not
    HTTP at all (the gateway closes those connections)."""
    word = "".join(rng.choice("abcdefghijklmnopqrstuvwxyz0123456789%") for _ in range(12))
    auth = f"Authorization: Bearer {TOKEN}\r\n"
    kind = rng.randrange(6)
    if kind == 0:
        return f"GET /api/v1/{word}/{rng.random()} HTTP/1.1\r\nHost: x\r\n\r\n".encode()
    if kind == 1:
        return f"GET /api/v1/sensors/{word} HTTP/1.1\r\nHost: x\r\n{auth}\r\n".encode()
    if kind == 2:
        return (f"POST /api/v1/sensors/a1/commands/{word} HTTP/1.1\r\nHost: x\r\n"
                f"Authorization: Bearer {word}\r\nContent-Length: 3\r\n\r\n{{x}}").encode()
    if kind == 3:
        body = word * 8
        return (f"POST /api/v1/sensors/a1/commands/set_zero_type HTTP/1.1\r\nHost: x\r\n"
                f"{auth}Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
                f"\r\n{body}").encode()
    if kind == 4:
        return f"DELETE /api/v1/health?{word}={word} HTTP/1.1\r\nHost: x\r\n\r\n".encode()
    return f"{word} \x01\x02 {word}\r\n\r\n".encode()  # not HTTP: closed


async def _garbage_worker(port: int, count: int, seed: int) -> int:
    rng = random.Random(seed)
    sent = 0
    reader: asyncio.StreamReader | None = None
    writer: asyncio.StreamWriter | None = None
    while sent < count:
        if writer is None or reader is None:
            reader, writer = await asyncio.open_connection(HOST, port,
                                                           local_addr=("127.0.0.2", 0))
        writer.write(garbage_request(rng))
        sent += 1
        try:
            head = await reader.readuntil(b"\r\n\r\n")
            length = next((int(line.split(b":")[1]) for line in head.split(b"\r\n")
                           if line.lower().startswith(b"content-length:")), 0)
            await reader.readexactly(length)
            if b"connection: close" in head.lower():
                raise ConnectionError
        except (ConnectionError, asyncio.IncompleteReadError):
            writer.close()
            reader = writer = None
    if writer is not None:
        writer.close()
    return sent


async def garbage(port: int, total: int, workers: int = 20) -> int:
    counts = await asyncio.gather(*(_garbage_worker(port, total // workers, i)
                                    for i in range(workers)))
    return sum(counts)


# ------------------------------------------------------------------ the run


async def measure(args: argparse.Namespace, folder: Path) -> dict[str, Any]:
    from support.harness import free_port

    sims = {"a": [make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST),
                  make_sensor(WireProtocol.NATIVE, Series.VG, 1, baud=FAST)],
            "b": [make_sensor(WireProtocol.MODBUS, Series.AH, 1, baud=FAST)]}
    ports = {name: free_port() for name in ("modbus", "http", "opcua")}
    env = dict(item.split("=", 1) for item in args.env)
    samples: dict[str, Any] = {}
    with Mosquitto(folder) as broker, simulated(sims["a"]) as a, simulated(sims["b"]) as b:
        gw = Gateway(folder, config_yaml({"a": a.path, "b": b.path}, ports, broker,
                                         folder / "pki"), args.trace, env)
        try:
            await _until_http(ports["http"], gw)
            await asyncio.sleep(args.settle)
            samples["start"] = await _steady(gw, args.settle)
            for n in range(1, args.rounds + 1):
                await _trickle(args, ports, gw, samples, f"round {n}: ")
                began = time.monotonic()
                sent = await garbage(ports["http"], args.garbage)
                took = time.monotonic() - began
                samples[f"round {n}: garbage ({sent} in {took:.0f} s), at its end"] = \
                    await gw.figures()
                await asyncio.sleep(args.settle)
                samples[f"round {n}: garbage, settled"] = await gw.figures()
            samples["after malloc_trim(0)"] = await gw.figures(trim=True)
        finally:
            gw.stop()
    return samples


async def _steady(gw: Gateway, settle: float) -> dict[str, Any]:
    """The figures once the gateway has settled after its start (the OPC UA server
    builds its address space for a while; under tracemalloc, for long)."""
    await asyncio.sleep(settle)
    last = await gw.figures()
    while True:
        await asyncio.sleep(settle)
        now = await gw.figures()
        if abs(now.get("traced_mb", 0) - last.get("traced_mb", 0)) < 0.2 and \
                abs(now["rss_mb"] - last["rss_mb"]) < 0.5:
            return now
        last = now


async def _trickle(args: argparse.Namespace, ports: dict[str, int], gw: Gateway,
                   samples: dict[str, Any], prefix: str) -> None:
    swarms = [Swarm(ports["http"], args.trickle // 2, trickle(PARTIAL_HEADERS)),
              Swarm(ports["modbus"], args.trickle - args.trickle // 2, trickle(PARTIAL_MBAP))]
    for swarm in swarms:
        swarm.start()
    await asyncio.sleep(args.hold)
    samples[f"{prefix}trickle, at its end"] = await gw.figures()
    for swarm in swarms:
        await swarm.stop()
    await asyncio.sleep(args.settle)
    samples[f"{prefix}trickle, settled"] = await gw.figures()


async def _until_http(port: int, gw: Gateway) -> None:
    for _ in range(600):
        if gw.process.poll() is not None:
            raise RuntimeError("the gateway exited")
        with contextlib.suppress(OSError):
            _, writer = await asyncio.open_connection(HOST, port)
            writer.close()
            return
        await asyncio.sleep(0.1)
    raise RuntimeError("the gateway's HTTP did not come up")


# ------------------------------------------------------------------ start-up


def _front_ends_yaml(ports: dict[str, int], broker: Mosquitto, pki: Path) -> str:
    return f"""modbus: {{listen: '{HOST}:{ports['modbus']}'}}
mqtt: {{url: '{broker.url}', homeassistant_discovery: true, sparkplug: {{group_id: rss}}}}
http: {{listen: '{HOST}:{ports['http']}'}}
opcua: {{listen: '{HOST}:{ports['opcua']}', allow_none: true, pki_dir: '{pki}'}}
"""


def _third_party_imports() -> list[str]:
    """Every import statement of another package's modules that the gateway's modules
    run as they load (their sources read with ``ast``: the statements at the top
    level, and in a ``try`` there; not those in a function, which may never run, or
    under ``if TYPE_CHECKING``), as written: ``from pkg import name`` may load a
    submodule ``name``."""
    found: set[str] = set()
    for source in (Path(__file__).resolve().parents[1] / "imu_gateway").rglob("*.py"):
        body = ast.parse(source.read_text()).body
        for node in body + [n for t in body if isinstance(t, ast.Try) for n in t.body]:
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names = [node.module]
            else:
                continue
            if all(name.split(".")[0] not in
                   {*sys.stdlib_module_names, "imu_gateway", "__future__"} for name in names):
                found.add(ast.unparse(node))
    return sorted(found)


def libraries_alone() -> float:
    """VmRSS (MB) of a bare Python process that has run ``_third_party_imports()``
    (one that fails, an optional dependency missing, is left out): the floor under
    the gateway's own figure with every front end on."""
    code = ("import sys\nfor statement in sys.argv[1:]:\n"
            "    try: exec(statement)\n    except ImportError: pass\n"
            "print(next(line.split()[1] for line in open('/proc/self/status')"
            " if line.startswith('VmRSS')))")
    done = subprocess.run([sys.executable, "-c", code, *_third_party_imports()],
                          capture_output=True, text=True, check=True)
    return int(done.stdout) / 1024


def _start_once(config: Path) -> tuple[subprocess.Popen[str], float, float]:
    """``imu-gateway run`` on ``config`` until its first reading: the process, the
    seconds that took, and its VmRSS (MB) then."""
    began = time.monotonic()
    process = subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c", str(config)],
                               stderr=subprocess.PIPE, text=True)
    assert process.stderr is not None
    for line in process.stderr:
        if ": online" in line:
            took = time.monotonic() - began
            # the rest of the log is not needed, but its pipe must not fill up
            threading.Thread(target=process.stderr.read, daemon=True).start()
            return process, took, rss_mb(process.pid)
    raise RuntimeError(f"the gateway exited: {process.wait()}")


async def _clients(ports: dict[str, int], broker: Mosquitto, hold: float) -> None:
    """Two clients of each front end, for ``hold`` seconds."""
    from asyncua import Client, ua

    async def subscriber() -> None:
        async with Client(f"opc.tcp://{HOST}:{ports['opcua']}/") as client:
            idx = await client.get_namespace_index("urn:imu-gateway")
            nodes = [client.get_node(ua.NodeId(f"rss.Sensors.{s}.Angles.{f}", idx))
                     for s in ("a1", "a2", "b1") for f in ("pitch", "roll", "yaw")]
            subscription = await client.create_subscription(100, None)
            await subscription.subscribe_data_change(nodes)
            await asyncio.sleep(hold)

    recorders = [Recorder(broker, "imu/#"), Recorder(broker, "spBv1.0/#")]
    clients = [ModbusPoller(ports["modbus"], [1, 2, 3]).run(),
               ModbusPoller(ports["modbus"], [1, 2, 3]).run(),
               HttpPoller(ports["http"], ["a1", "a2", "b1"]).run(), SseReader(ports["http"]).run()]
    tasks = [asyncio.create_task(c) for c in clients]
    try:
        await asyncio.gather(subscriber(), subscriber())
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for recorder in recorders:
            recorder.close()


async def start_up(args: argparse.Namespace, folder: Path) -> dict[str, list[float]]:
    from support.harness import free_port

    sims = {"a": [make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST),
                  make_sensor(WireProtocol.NATIVE, Series.VG, 1, baud=FAST)],
            "b": [make_sensor(WireProtocol.MODBUS, Series.AH, 1, baud=FAST)]}
    ports = {name: free_port() for name in ("modbus", "http", "opcua")}
    figures: dict[str, list[float]] = {}
    with Mosquitto(folder) as broker, simulated(sims["a"]) as a, simulated(sims["b"]) as b:
        buses = config_yaml({"a": a.path, "b": b.path}, ports, broker, folder / "pki")
        buses = buses[:buses.index("modbus:")]
        configs = {"bus only": buses,
                   "every front end": buses + _front_ends_yaml(ports, broker, folder / "pki")}
        for _ in range(args.start):
            for name, text in configs.items():
                path = folder / "gateway.yaml"
                path.write_text(text)
                process, took, rss = _start_once(path)
                try:
                    figures.setdefault(f"{name}: first reading, s", []).append(took)
                    figures.setdefault(f"{name}: VmRSS then, MB", []).append(rss)
                    if name == "every front end":
                        await _clients(ports, broker, args.hold)
                        figures.setdefault(f"{name}: VmRSS after {args.hold:g} s of 2 "
                                           "clients each, MB", []).append(rss_mb(process.pid))
                finally:
                    process.send_signal(signal.SIGINT)
                    process.wait(20)
            figures.setdefault("the libraries alone (a bare process importing them): "
                               "VmRSS, MB", []).append(libraries_alone())
    return figures


def main() -> int:
    if sys.argv[1:2] == ["--child"]:
        return child(sys.argv[2], sys.argv[3], "--trace" in sys.argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trickle", type=int, default=400)
    parser.add_argument("--garbage", type=int, default=57_000)
    parser.add_argument("--hold", type=float, default=30.0, help="trickle for this long, s")
    parser.add_argument("--settle", type=float, default=10.0, help="quiet after each, s")
    parser.add_argument("--rounds", type=int, default=1, help="both attacks, this many times")
    parser.add_argument("--trace", action="store_true", help="the gateway under tracemalloc")
    parser.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                        help="for the gateway: MALLOC_ARENA_MAX=2, PYTHONMALLOC=malloc, …")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--start", type=int, default=0, metavar="N",
                        help="instead: start-up time and VmRSS, N starts of each")
    args = parser.parse_args()
    if args.start:
        with tempfile.TemporaryDirectory(prefix="rss-") as folder:
            starts = asyncio.run(start_up(args, Path(folder)))
        for name, values in starts.items():
            print(f"{name}: {min(values):.2f}-{max(values):.2f} "
                  f"(median {sorted(values)[len(values) // 2]:.2f}; {len(values)} runs)")
        if args.json:
            args.json.write_text(json.dumps(starts, indent=2))
        return 0
    with tempfile.TemporaryDirectory(prefix="rss-") as folder:
        samples = asyncio.run(measure(args, Path(folder)))
    for name, figures in samples.items():
        if not isinstance(figures, dict):
            print(f"{name}: {figures}")
            continue
        traced = f", traced {figures['traced_mb']:.1f} MB" if "traced_mb" in figures else ""
        print(f"{name}: RSS {figures['rss_mb']:.1f} MB, {figures['threads']} threads{traced}")
        for line in figures.get("top", [])[:8]:
            print(f"    {line}")
    if args.json:
        args.json.write_text(json.dumps(samples, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
