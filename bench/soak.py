"""The soak: the real gateway process under steady load on every front end, while
faults and hostile clients come one after another, each followed by a measured
recovery; at the end, a verdict on leaks, the serial line's rules and the front ends.

Run: ``scripts/soak --minutes N [--json PATH] [--only PHASE,...] [--keep DIR]``
(docs/reliability.md explains the phases, the checks and the figures).

What runs, each in a process of its own as in a plant:

* two simulated RS-485 lines (``imu_gateway.simulator``), each reached through a symlink
  that an unplug removes and a replug puts back:
  ``line-a``: native at 115200, an AH and a VG that answer 5-40 ms late (jittered);
  ``line-b``: Modbus RTU at 115200, an AH streaming at 20 Hz next to a VG polled at
  10 Hz.  They run at real-time priority where allowed: they play hardware, which
  never waits for the gateway's CPU;
* mosquitto on a free port;
* ``python -m imu_gateway run`` with Modbus TCP (writes allowed), MQTT 5 (commands, Home
  Assistant discovery) and HTTP (commands) on; at real-time priority (SCHED_FIFO 10) as
  the systemd unit runs it, unless ``--gateway-priority normal``.

The steady load (``hostile.py``): a Modbus TCP poller, REST polling, an SSE reader,
an MQTT subscriber counting ``seq`` gaps, an MQTT client sending a command a second, and
a Modbus TCP client writing a setting that is not idempotent every 3 s (each write the
sensor hears more often than it was sent is a failure: a write sent twice).

Exit status: 0 when every check passed, 1 when one failed (the summary says which),
2 when the soak could not be set up.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import multiprocessing
import os
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import hostile as h
from support.broker import Mosquitto
from support.harness import free_port

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import PtyBus, make_sensor
from imu_gateway.simulator.motion import Motion

ROOT = Path(__file__).resolve().parents[1]
GATEWAY_ID = "soak"
BASE = f"imu/{GATEWAY_ID}"
TOKEN = "soak-token"
SIM_PRIORITY, GATEWAY_PRIORITY = 20, 10  # SCHED_FIFO: the "hardware" above the gateway
NOISE_BURSTS = 20.0  # bursts of line noise per second during the noise phase
CORRUPT = 0.05  # share of frames with a flipped bit during the noise phase
STREAM_WRITES = {"set_output_type", "set_output_rate", "register 0x1B", "register 0x1C"}
STOP_WRITES = {"set_output_rate", "register 0x1B"}  # what stopping a stream writes
RECOVERY_TIMEOUT = 60.0  # a fault not healed this long after it ended is a failure
PHASE_GRACE = 60.0  # a phase's clients not ended this long after its hold: the rig's fault
SETTLE = 1.5  # seconds after a recovery before the resources are sampled
STALL_MAX = 20.0  # how long a stalled sensor may take to be reported offline


# ------------------------------------------------------------------ the lines


@dataclass(frozen=True)
class SensorSpec:
    name: str
    series: str
    address: int
    rate: str  # its config: "poll_hz: 10" or "stream_hz: 20"
    delay_ms: float  # answer delay, plus up to jitter_ms
    jitter_ms: float

    @property
    def streams(self) -> bool:
        return self.rate.startswith("stream_hz")


@dataclass(frozen=True)
class Line:
    name: str
    protocol: str
    baud: int
    sensors: tuple[SensorSpec, ...]


LINES = (
    Line("line-a", "native", 115200, (
        SensorSpec("a1", "AH", 1, "poll_hz: 10", 5, 35),
        SensorSpec("a2", "VG", 2, "poll_hz: 10", 5, 35))),
    Line("line-b", "modbus", 115200, (
        SensorSpec("b1", "AH", 1, "stream_hz: 20", 2, 3),
        SensorSpec("b2", "VG", 2, "poll_hz: 10", 2, 3))),
)
SENSORS = [s for line in LINES for s in line.sensors]
UNIT = {s.name: i + 1 for i, s in enumerate(SENSORS)}  # unit ids in file order


def config_yaml(links: dict[str, str], modbus: int, http: int, mqtt_port: int) -> str:
    out = [f"gateway_id: {GATEWAY_ID}", "buses:"]
    for line in LINES:
        out += [f"  - name: {line.name}", f"    port: {links[line.name]}",
                f"    baudrate: {line.baud}", f"    protocol: {line.protocol}", "    sensors:"]
        out += [f"      - {{name: {s.name}, series: {s.series}, address: {s.address}, {s.rate}}}"
                for s in line.sensors]
    out += [f"modbus: {{listen: '127.0.0.1:{modbus}', allow_writes: true}}",
            f"mqtt: {{url: 'mqtt://127.0.0.1:{mqtt_port}', protocol: 5, allow_commands: true,",
            "       homeassistant_discovery: true}",
            f"http: {{listen: '127.0.0.1:{http}', token: {TOKEN}, allow_commands: true}}"]
    return "\n".join(out) + "\n"


# ------------------------------------------------------------------ the simulators


class SoakBus(PtyBus):
    """PtyBus draws its noise schedule once, when it starts serving, from ``noise_rate``:
    a rate of 0 then means never.  So the line is built with the noise phase's rate and
    lets the bursts through only while that phase is on."""

    noise_on = False

    def _inject_noise(self) -> None:
        if self.noise_on:
            super()._inject_noise()


def _realtime(priority: int) -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError):
        return False
    return True


def serve_line(line: Line, link: str, seed: int, pipe: Connection) -> None:
    """The simulator process of one line: serves it and carries out the parent's
    requests (faults, noise, unplug, replug, stats) until told to stop."""
    _realtime(SIM_PRIORITY)
    sensors = [make_sensor(WireProtocol[line.protocol.upper()], Series[s.series], s.address,
                           baud=line.baud, source=Motion.from_seed(seed + i),
                           answer_delay=s.delay_ms / 1000, jitter=s.jitter_ms / 1000,
                           seed=seed + i)
               for i, s in enumerate(line.sensors)]
    bus = SoakBus(sensors, noise_rate=NOISE_BURSTS, seed=seed, link=link)
    names = [s.name for s in line.sensors]
    asyncio.run(_serve(bus, names, pipe))


async def _serve(bus: SoakBus, names: list[str], pipe: Connection) -> None:
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    by_name = dict(zip(names, bus.sensors, strict=True))

    async def carry_out(op: str, *args: Any) -> Any:
        match op:
            case "faults":
                for sensor in [by_name[args[0]]] if args[0] else bus.sensors:
                    for key, value in args[1].items():
                        setattr(sensor.faults, key, value)
            case "noise":
                bus.noise_on = args[0]
            case "unplug":
                bus.unplug()
            case "replug":
                return bus.replug()
        return _line_stats(bus, names)

    def listen() -> None:
        while True:
            try:
                request = pipe.recv()
            except EOFError:  # the soak is gone: so is this line
                request = ("stop",)
            if request[0] == "stop":
                loop.call_soon_threadsafe(stop.set)
                return
            pipe.send(asyncio.run_coroutine_threadsafe(carry_out(*request), loop).result())

    def ready() -> None:
        pipe.send(bus.path)
        threading.Thread(target=listen, daemon=True).start()

    await bus.serve(stop, on_ready=ready)
    pipe.send(_line_stats(bus, names))


def _line_stats(bus: PtyBus, names: list[str]) -> dict[str, Any]:
    stats = bus.stats
    # A simulator held off its CPU by the machine, or whose pty handed the gateway's
    # bytes over late, stops playing hardware: what follows such a hold or lag is
    # counted apart (simulator/bus.py: HoldWatch, WireWatch), not against the gateway.
    return {"overlaps": stats.masters_overlaps, "collisions": stats.masters_collisions,
            "holds": stats.holds, "held_s": round(stats.held_s, 3),
            "lags": stats.lags, "lagged_s": round(stats.lagged_s, 3),
            "after_holds": stats.overlaps_after_hold + stats.collisions_after_hold,
            "noise_bytes": stats.noise_bytes, "answer_frames": stats.answer_frames,
            "incidents": stats.incidents[:3],
            "writes": {n: dict(s.writes_heard) for n, s in zip(names, bus.sensors, strict=True)}}


class SimLine:
    """The parent's end of one simulator process."""

    def __init__(self, line: Line, link: str, seed: int) -> None:
        context = multiprocessing.get_context("spawn")
        self.line = line
        self._pipe, theirs = context.Pipe()
        self._lock = threading.Lock()
        self.process = context.Process(target=serve_line, args=(line, link, seed, theirs),
                                       daemon=True, name=f"sim-{line.name}")
        self.process.start()
        if not self._pipe.poll(30):
            raise RuntimeError(f"the simulator of {line.name} did not start")
        self.path = self._pipe.recv()
        self.final: dict[str, Any] | None = None

    def call(self, *request: Any) -> Any:
        with self._lock:
            self._pipe.send(request)
            if not self._pipe.poll(15):
                raise RuntimeError(f"the simulator of {self.line.name} does not answer")
            return self._pipe.recv()

    async def ask(self, *request: Any) -> Any:
        return await asyncio.to_thread(self.call, *request)

    def stop(self) -> dict[str, Any]:
        if self.final is None:
            with self._lock:
                self._pipe.send(("stop",))
                self.final = self._pipe.recv() if self._pipe.poll(15) else {}
            self.process.join(10)
        return self.final


# ------------------------------------------------------------------ broker, gateway, sampler


CLIENT_NICE = -10  # the clients and the broker stand for other machines (see below)


def favour(pid: int = 0) -> None:
    """The soak's clients and the broker stand for machines elsewhere on the network:
    the CPU phase loads the gateway's machine, not theirs.  They run at nice -10 where
    allowed, so that the busy loops do not starve them and what they measure is the
    gateway.  (On Linux this is per thread: threads made afterwards inherit it.)"""
    with contextlib.suppress(PermissionError, OSError):
        os.setpriority(os.PRIO_PROCESS, pid, CLIENT_NICE)


class QuietMosquitto(Mosquitto):
    """tests/support/broker.py's broker logs every packet: over a long soak that is a large
    file of nothing.  Here it logs what went wrong and who connected."""

    def _config(self) -> Path:
        path = super()._config()
        path.write_text(path.read_text().replace(
            "log_type all", "log_type error\nlog_type warning\nlog_type notice"))
        return path

    def start(self) -> None:
        super().start()
        if self.process is not None:
            favour(self.process.pid)


def realtime_allowed() -> bool:
    chrt = shutil.which("chrt")
    return chrt is not None and subprocess.run(
        [chrt, "--fifo", str(GATEWAY_PRIORITY), "true"], capture_output=True).returncode == 0


class GatewayProcess:
    """``python -m imu_gateway run`` with its log (stdout and stderr) in a file."""

    def __init__(self, config: Path, log: Path, realtime: bool) -> None:
        self.log = log
        prefix = ["chrt", "--fifo", str(GATEWAY_PRIORITY)] if realtime else []
        with log.open("wb") as out:  # the child keeps its own descriptor
            self.proc = subprocess.Popen(
                [*prefix, sys.executable, "-m", "imu_gateway", "run", "-c", str(config)],
                stdout=out, stderr=subprocess.STDOUT, cwd=ROOT)
        self.exit_status: int | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def log_size(self) -> int:
        return self.log.stat().st_size

    def log_since(self, offset: int) -> str:
        with self.log.open("rb") as f:
            f.seek(offset)
            return f.read().decode(errors="replace")

    def stop(self) -> int | None:
        """SIGTERM, as systemd stops it; its exit status (None: it had to be killed)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.exit_status = self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        else:
            self.exit_status = self.proc.returncode
        return self.exit_status


@dataclass(frozen=True)
class Sample:
    t: float  # time.monotonic()
    rss_mb: float
    fds: int
    threads: int


def sample(pid: int) -> Sample | None:
    """The process's resident memory, open descriptors and threads (from /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    return Sample(time.monotonic(), int(fields["VmRSS"].split()[0]) / 1024, fds,
                  int(fields["Threads"]))


# ------------------------------------------------------------------ the soak's world


@dataclass
class Clients:
    """The well-behaved clients, running all the time."""

    modbus: h.ModbusPoller
    http: h.HttpPoller
    sse: h.SseReader
    watcher: h.MqttWatcher
    mqtt: h.MqttCommander
    writer: h.ModbusWriter

    def records(self) -> dict[str, h.Record]:
        return {"modbus": self.modbus.record, "mqtt": self.mqtt.record,
                "http": self.http.record}


class Soak:
    """Everything the phases act on: the broker, the lines, the gateway, the clients,
    the resource samples, and the writes the soak itself asked for."""

    def __init__(self, folder: Path, args: argparse.Namespace) -> None:
        self.folder, self.args = folder, args
        self.modbus_port, self.http_port = free_port(), free_port()
        self.broker = QuietMosquitto(folder)
        self.lines: dict[str, SimLine] = {}
        self.realtime = args.gateway_priority == "realtime" and realtime_allowed()
        self.gateway: GatewayProcess | None = None
        self.clients: Clients | None = None
        self.samples: list[Sample] = []
        self.asked: Counter[tuple[str, str]] = Counter()  # (sensor, write) the soak sent
        self._tasks: list[asyncio.Task[None]] = []
        self._watcher_closed = False

    @property
    def gw(self) -> GatewayProcess:
        assert self.gateway is not None
        return self.gateway

    @property
    def cl(self) -> Clients:
        assert self.clients is not None
        return self.clients

    def start_processes(self) -> None:
        self.broker.start()
        for seed, line in enumerate(LINES):
            link = str(self.folder / f"{line.name}.tty")
            self.lines[line.name] = SimLine(line, link, seed * 10)
        config = self.folder / "gateway.yaml"
        config.write_text(config_yaml({n: str(self.folder / f"{n}.tty") for n in self.lines},
                                      self.modbus_port, self.http_port, self.broker.port))
        self.gateway = GatewayProcess(config, self.folder / "gateway.log", self.realtime)

    async def start_clients(self) -> None:
        favour()  # after the gateway and the simulators started: they keep their own
        await self.until(self._http_up, 30, "the gateway's HTTP API did not come up")
        watcher = h.MqttWatcher(self.broker.port, BASE)
        self.clients = Clients(h.ModbusPoller(self.modbus_port, sorted(UNIT.values())),
                               h.HttpPoller(self.http_port, [s.name for s in SENSORS]),
                               h.SseReader(self.http_port), watcher,
                               h.MqttCommander(watcher, "a1"),
                               h.ModbusWriter(self.modbus_port, UNIT["a1"], 1000, 0,
                                              self._asked_zero_type))
        for run in (self.cl.modbus.run, self.cl.http.run, self.cl.sse.run, self.cl.mqtt.run,
                    self.cl.writer.run, self._sample):
            self._tasks.append(asyncio.create_task(run()))
        await self.until(lambda: everything_ok(self, 0.0), 60,
                         "the sensors and front ends were not all up within 60 s")

    def _asked_zero_type(self) -> None:
        """zero type "absolute" (register 1000 = 0) to a1: not idempotent, so never
        sent twice, however its answer was lost."""
        self.asked["a1", "set_zero_type"] += 1

    async def _http_up(self) -> bool:
        if not self.gw.alive():
            raise RuntimeError("the gateway exited:\n" + self.gw.log_since(0)[-2000:])
        return await http_ok(self, 0.0)

    async def _sample(self) -> None:
        while True:
            found = sample(self.gw.pid)
            if found is not None:
                self.samples.append(found)
            await asyncio.sleep(1.0)

    async def stop_clients(self) -> None:
        await h.ended(self._tasks)
        self._tasks.clear()

    def stop_processes(self) -> None:
        """The gateway first (it stops the stream it set up), then what it talks to;
        each step at most once."""
        if self.clients is not None and not self._watcher_closed:
            self.clients.watcher.close()
            self._watcher_closed = True
        if self.gateway is not None:
            self.gateway.stop()
        for line in self.lines.values():
            line.stop()
        self.broker.stop()

    async def until(self, check: Callable[[], Awaitable[bool]], timeout: float,
                    failure: str | None = None) -> float | None:
        """Seconds until ``check()`` holds (polled every 0.1 s), or None at the timeout
        (or RuntimeError(failure) when given)."""
        started = time.monotonic()
        while time.monotonic() - started < timeout:
            if await check():
                return time.monotonic() - started
            if self.gateway is not None and not self.gateway.alive():
                break  # nothing will heal now
            await asyncio.sleep(0.1)
        if failure is not None:
            raise RuntimeError(failure)
        return None

    async def statuses(self) -> dict[str, str]:
        try:
            return {s["name"]: s["status"] for s in
                    await h.http_json(self.http_port, "/api/v1/sensors")}
        except (OSError, TimeoutError, ValueError):
            return {}

    async def watch(self, seconds: float, names: list[str]) -> dict[str, set[str]]:
        """The statuses each of ``names`` showed over the next ``seconds``."""
        seen: dict[str, set[str]] = {n: set() for n in names}
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            now = await self.statuses()
            for name in names:
                if name in now:
                    seen[name].add(now[name])
            await asyncio.sleep(0.2)
        return seen

    async def writes(self) -> dict[str, dict[str, int]]:
        heard: dict[str, dict[str, int]] = {}
        for line in self.lines.values():
            heard.update((await line.ask("stats"))["writes"])
        return heard

    async def line_counts(self) -> Counter[str]:
        counts: Counter[str] = Counter()
        for line in self.lines.values():
            stats = await line.ask("stats")
            counts.update(overlaps=stats["overlaps"], collisions=stats["collisions"])
        return counts


# ------------------------------------------------------------------ health checks


async def modbus_ok(soak: Soak, since: float) -> bool:
    return await h.modbus_once(soak.modbus_port)


async def http_ok(soak: Soak, since: float) -> bool:
    try:
        status, _ = await h.http_get(soak.http_port, "/api/v1/health")
    except (OSError, TimeoutError, ValueError):
        return False
    return status == 200


async def mqtt_ok(soak: Soak, since: float) -> bool:
    """States flow (one came after ``since``) and the gateway's status is online."""
    watcher = soak.cl.watcher
    with watcher.lock:
        status = watcher.status[-1][1] if watcher.status else ""
        return status == "online" and watcher.last_state_at > since


async def sensors_ok(soak: Soak, since: float) -> bool:
    now = await soak.statuses()
    return bool(now) and all(now.get(s.name) == "ok" for s in SENSORS)


async def everything_ok(soak: Soak, since: float) -> bool:
    """Every sensor ok, and every front end answers."""
    for check in (sensors_ok, modbus_ok, http_ok, mqtt_ok):
        if not await check(soak, since):
            return False
    return True


async def broker_back(soak: Soak, since: float) -> bool:
    """The gateway said "online" again after the broker came back, and states flow."""
    return soak.cl.watcher.online_since(since) and await everything_ok(soak, since)


# ------------------------------------------------------------------ the phases


@dataclass
class Outcome:
    notes: str = ""
    problems: list[str] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)


Fault = Callable[[Soak, float], Awaitable[Outcome]]
Healthy = Callable[[Soak, float], Awaitable[bool]]


@dataclass(frozen=True)
class Phase:
    name: str
    what: str  # one line for the report
    fault: Fault  # does the fault for the hold and undoes it; what it saw
    healthy: Healthy = everything_ok  # the recovery check, given when the fault ended
    expect_down: frozenset[str] = frozenset()  # clients allowed to go unanswered


async def modbus_no_reader(soak: Soak, hold: float) -> Outcome:
    flood = h.ModbusFlood(soak.modbus_port, UNIT["b2"])
    await asyncio.to_thread(flood.start)
    await asyncio.sleep(hold)
    seen = await asyncio.to_thread(flood.stop)
    kept = seen["stopped_reading"] or seen["closed_by_gateway"]
    notes = (f"sent {seen['requests_sent']} requests; the gateway "
             + ("closed the connection" if seen["closed_by_gateway"] else
                f"stopped reading ({seen['unread_bytes'] / 1e6:.2f} MB left unread)"
                if seen["stopped_reading"] else "read them all"))
    problems = [] if kept else [
        "no back-pressure: the gateway read every request of a client that reads no answer"]
    return Outcome(notes, problems, seen)


async def modbus_trickle(soak: Soak, hold: float) -> Outcome:
    swarm = h.Swarm(soak.modbus_port, 150, h.trickle(h.PARTIAL_MBAP))
    swarm.start()
    await asyncio.sleep(hold)
    seen = await swarm.stop()
    return Outcome(_swarm_note("150 trickling", seen), data=seen)


def _swarm_note(what: str, seen: dict[str, Any]) -> str:
    life = seen["median_life_s"]
    return (f"{what}: {seen['opened']} opened, {seen['connect_failed']} failed to "
            f"connect, {seen['closed_by_gateway']} closed by the gateway"
            + (f" ({seen['closed_within_0.5_s']} within 0.5 s, median after {life} s)"
               if life is not None else ""))


async def modbus_half_close(soak: Soak, hold: float) -> Outcome:
    """zero type "absolute" (register 1000 = 0) to a1, each write followed by a
    half-close; the answer is owed all the same."""
    results = []
    for _ in range(3):
        soak.asked["a1", "set_zero_type"] += 1
        results.append(await h.write_then_half_close(soak.modbus_port, UNIT["a1"], 1000, 0))
        await asyncio.sleep(hold / 3)
    lost = [f"{seconds:.1f} s: {what}" for answered, seconds, what in results if not answered]
    worst = max(seconds for _, seconds, _ in results)
    problems = [f"{len(lost)} of 3 writes followed by a half-close got no answer "
                f"({'; '.join(lost)})"] if lost else []
    return Outcome(f"{3 - len(lost)} of 3 answered, slowest {worst * 1000:.0f} ms", problems)


async def http_idle(soak: Soak, hold: float) -> Outcome:
    idle = h.Swarm(soak.http_port, 400, h.idle)
    partial = h.Swarm(soak.http_port, 50, h.trickle(h.PARTIAL_HEADERS))
    idle.start()
    partial.start()
    await asyncio.sleep(hold)
    seen = {"idle": await idle.stop(), "partial_headers": await partial.stop()}
    return Outcome(f"{_swarm_note('400 idle', seen['idle'])}; "
                   f"{_swarm_note('50 partial headers', seen['partial_headers'])}", data=seen)


async def http_big_headers(soak: Soak, hold: float) -> Outcome:
    """50 connections each sending a header line that never ends, as fast as the
    gateway takes it: each must get a 431, and what they hold stay bounded."""
    flood = h.EndlessHeader()
    swarm = h.Swarm(soak.http_port, 50, flood.behave)
    before = sample(soak.gw.pid)
    peak = before.rss_mb if before else 0.0
    swarm.start()
    end = time.monotonic() + hold
    while time.monotonic() < end:
        now = sample(soak.gw.pid)
        peak = max(peak, now.rss_mb if now else 0.0)
        await asyncio.sleep(0.05)
    seen = {**await swarm.stop(), "answers": flood.answers, "sent_mb": flood.sent / 1e6,
            "rss_growth_mb": round(peak - before.rss_mb, 1) if before else None}
    problems = []
    if set(flood.answers) - {"431"}:
        problems.append(f"endless headers answered otherwise than 431: {flood.answers}")
    if before is not None and peak - before.rss_mb >= 20:
        problems.append(f"endless headers grew the gateway's RSS by "
                        f"{peak - before.rss_mb:.0f} MB (at most 20)")
    return Outcome(f"{_swarm_note('50 endless headers', seen)}; answers {flood.answers}; "
                   f"{flood.sent / 1e6:.0f} MB sent; RSS +{seen['rss_growth_mb']} MB",
                   problems, seen)


async def mqtt_deputy(soak: Soak, hold: float) -> Outcome:
    """read_settings to a2 asking for its result on topics others trust: a sensor's
    state, a command (a1's save), Home Assistant's discovery, Sparkplug, the broker's
    $SYS.  Each must be refused on the default result topic, none answered there."""
    topic = f"{BASE}/a2/cmd/read_settings"
    forbidden = [f"{BASE}/a2/state", f"{BASE}/a1/cmd/save",
                 "homeassistant/sensor/soak/config", "spBv1.0/soak/NCMD/edge", "$SYS/soak"]
    saves = (await soak.writes())["a1"].get("save", 0)
    since, log0 = time.monotonic(), soak.gw.log_size()
    listener = await asyncio.to_thread(h.Listener, soak.broker.port, forbidden, b"soak")
    try:
        refused = await asyncio.to_thread(h.publish_hostile, soak.broker.port, [
            (topic, b"{}", False, h.response_topic(t)) for t in forbidden])
        await asyncio.sleep(max(hold, 2.0))
    finally:
        await asyncio.to_thread(listener.close)
    notes, problems = _broker_kept(soak, since, log0, refused)
    with soak.cl.watcher.lock:
        refusals = sum(b"response topic" in p for t, name, p in soak.cl.watcher.results
                       if t >= since and name == f"{topic}/result")
    if listener.got:
        problems.append(f"results published where they were refused: {listener.got}")
    if refusals < len(forbidden) - len(refused):
        problems.append(f"{refusals} refusals for {len(forbidden) - len(refused)} requests")
    ran = (await soak.writes())["a1"].get("save", 0) - saves
    if ran:
        problems.append(f"a result on a1's cmd/save made the gateway save a1 ({ran}x)")
    return Outcome(f"refusals on the default topic: {refusals}; results on forbidden "
                   f"topics: {len(listener.got)}; {notes}", problems,
                   {"refusals": refusals, "arrived": listener.got})


async def mqtt_bad_response(soak: Soak, hold: float) -> Outcome:
    """read_settings to a2 with a wildcard response topic and with the longest one a
    client can send (65,535 bytes: MQTT strings carry a 16-bit length, so 70 kB cannot
    be sent), and a command topic whose ``/result`` would be over that limit."""
    topic = f"{BASE}/a2/cmd/read_settings"
    long_sensor = "x" * (65535 - len(f"{BASE}//cmd/read_settings"))
    since, log0 = time.monotonic(), soak.gw.log_size()
    refused = await asyncio.to_thread(h.publish_hostile, soak.broker.port, [
        (topic, b"{}", False, h.response_topic("x/#")),
        (topic, b"{}", False, h.response_topic("r/" + "x" * 65533)),
        (f"{BASE}/{long_sensor}/cmd/read_settings", b"{}", False, None)])
    await asyncio.sleep(hold)
    notes, problems = _broker_kept(soak, since, log0, refused)
    with soak.cl.watcher.lock:
        answers = [json.loads(p) for t, name, p in soak.cl.watcher.results
                   if t >= since and name == f"{topic}/result"]
    refusals = [a.get("kind") for a in answers if not a.get("ok")]
    return Outcome(f"error results on the default topic: {refusals or 'none'}; {notes}",
                   problems)


def _broker_kept(soak: Soak, since: float, log0: int, refused: list[str]
                 ) -> tuple[str, list[str]]:
    """Did the gateway keep its broker connection through a hostile MQTT phase?"""
    log = soak.gw.log_since(log0)
    reconnects = log.count("mqtt: connected")
    with soak.cl.watcher.lock:
        offline = [t for t, text in soak.cl.watcher.status if t >= since and text != "online"]
    problems = []
    if reconnects or offline:
        problems.append(f"the gateway lost the broker ({reconnects} reconnects, "
                        f"{len(offline)} offline statuses)")
    notes = f"not sent: {'; '.join(refused)}" if refused else "all acknowledged by the broker"
    return notes, problems


async def mqtt_retained_clear(soak: Soak, hold: float) -> Outcome:
    """An empty retained message on a1's cmd/save, which is how a retained command is
    cleared: the broker delivers it to the gateway, which must run nothing."""
    before = (await soak.writes())["a1"].get("save", 0)
    since, log0 = time.monotonic(), soak.gw.log_size()
    refused = await asyncio.to_thread(h.publish_hostile, soak.broker.port,
                                      [(f"{BASE}/a1/cmd/save", b"", True, None)])
    await asyncio.sleep(max(hold, 2.0))  # a save would reach the sensor well within this
    ran = (await soak.writes())["a1"].get("save", 0) - before
    notes, problems = _broker_kept(soak, since, log0, refused)
    if ran:
        problems.append(f"an empty retained cmd/save made the gateway save a1 ({ran}x)")
    if "cmd/save" not in soak.gw.log_since(log0):
        problems.append("the gateway did not log the empty retained command")
    return Outcome(f"save heard by a1: {ran}; {notes}", problems)


async def broker_restart(soak: Soak, hold: float) -> Outcome:
    await asyncio.to_thread(soak.broker.stop)
    await asyncio.sleep(hold)
    await asyncio.to_thread(soak.broker.start)
    return Outcome(f"broker down {hold:.1f} s")


async def port_unplug(soak: Soak, hold: float) -> Outcome:
    line = soak.lines["line-b"]
    names = [s.name for s in line.line.sensors]
    await line.ask("unplug")
    seen = await soak.watch(hold, names)
    await line.ask("replug")
    offline = [n for n in names if "offline" in seen[n]]
    return Outcome(f"line-b unplugged {hold:.1f} s; reported offline: "
                   f"{', '.join(offline) or 'none'}")


async def noise(soak: Soak, hold: float) -> Outcome:
    for line in soak.lines.values():
        await line.ask("noise", True)
        await line.ask("faults", None, {"corrupt_rate": CORRUPT})
    seen = await soak.watch(hold, [s.name for s in SENSORS])
    for line in soak.lines.values():
        await line.ask("noise", False)
        await line.ask("faults", None, {"corrupt_rate": 0.0})
    offline = [n for n, statuses in seen.items() if "offline" in statuses]
    return Outcome(f"{NOISE_BURSTS:g} noise bursts/s, {CORRUPT:.0%} of frames corrupted; "
                   f"reported offline: {', '.join(offline) or 'none'}")


async def stall(soak: Soak, hold: float) -> Outcome:
    """a2 stops answering: it must be reported offline, then online once it is back."""
    line = soak.lines["line-a"]
    started = time.monotonic()
    await line.ask("faults", "a2", {"stalled": True})

    async def offline() -> bool:
        return (await soak.statuses()).get("a2") == "offline"

    took = await soak.until(offline, max(hold, STALL_MAX))
    await asyncio.sleep(max(0.0, started + hold - time.monotonic()))
    await line.ask("faults", "a2", {"stalled": False})
    if took is None:
        return Outcome("a2 stalled", ["a2 stalled and was never reported offline "
                                      f"(waited up to {max(hold, STALL_MAX):.0f} s)"])
    return Outcome(f"a2 reported offline {took:.1f} s after it stalled")


def burners() -> int:
    return 2 * (os.cpu_count() or 1)


async def cpu_load(soak: Soak, hold: float) -> Outcome:
    # at nice 0, like any other work on the gateway's machine (this thread is at -10)
    procs = [subprocess.Popen(["nice", "-n", str(-os.nice(0)), sys.executable, "-c",
                               "while True: pass"]) for _ in range(burners())]
    try:
        await asyncio.sleep(hold)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
    return Outcome(f"{len(procs)} busy loops on {os.cpu_count()} cores")


# The connection-heavy phases come first: memory Python keeps after a burst is then in
# every sample the leak trend compares, even in a run of a single cycle.
PHASES = (
    Phase("modbus-no-reader", "a Modbus TCP client pipelines 200,000 reads and reads no "
          "answer", modbus_no_reader),
    Phase("modbus-trickle", "150 Modbus TCP connections send a request one byte every 2 s",
          modbus_trickle),
    Phase("http-idle", "400 idle HTTP connections, 50 sending a header a byte every 2 s",
          http_idle),
    Phase("http-big-headers", "50 HTTP connections each sending a header line that "
          "never ends, as fast as the gateway takes it", http_big_headers),
    Phase("modbus-half-close", "3 Modbus writes, each followed by shutdown(SHUT_WR)",
          modbus_half_close),
    Phase("mqtt-bad-response", "MQTT 5 commands with response topic x/# and a 64 kB one; "
          "a command topic whose /result is over 64 kB", mqtt_bad_response),
    Phase("mqtt-deputy", "MQTT 5 commands asking for their result on a sensor's state, "
          "a command, HA discovery, Sparkplug and $SYS topics", mqtt_deputy),
    Phase("mqtt-retained-clear", "an empty retained message on a1/cmd/save",
          mqtt_retained_clear),
    Phase("broker-restart", "mosquitto stopped for the hold, started on the same port",
          broker_restart, broker_back, frozenset({"mqtt"})),
    Phase("port-unplug", "line-b's port disappears for the hold, comes back at its path",
          port_unplug),
    Phase("noise", "line noise and corrupted frames on both lines", noise),
    Phase("stall", "a2 stops answering (at least until it is reported offline)", stall),
    # A client starved of CPU may fall behind a stream; that is its own doing.
    Phase("cpu-load", "busy-loop processes, two per core", cpu_load,
          expect_down=frozenset({"sse"})),
)


# ------------------------------------------------------------------ running a phase


@dataclass
class PhaseResult:
    name: str
    cycle: int
    start: float  # time.monotonic(), as the simulators' incident times
    end: float  # recovered (or given up)
    hold_s: float
    recovery_s: float | None
    worst_ms: dict[str, float | None]  # each well-behaved client's slowest answer
    unanswered: dict[str, int]
    sse_drops: int
    sse_silence_s: float  # the longest time without an SSE event
    mqtt_gaps: int
    overlaps: int
    collisions: int
    rss_rise_mb: float  # the peak during the phase over the value before it
    counted: dict[str, float]  # what the gateway's own counters (health) say happened
    log_lines: int  # what the gateway logged meanwhile
    notes: str
    problems: list[str]
    data: dict[str, Any]


def _window_figures(soak: Soak, start: float, end: float
                    ) -> tuple[dict[str, float | None], dict[str, int], dict[str, str]]:
    worst: dict[str, float | None] = {}
    unanswered: dict[str, int] = {}
    why: dict[str, str] = {}
    for name, record in soak.cl.records().items():
        answers = record.window(start, end)
        latencies = [a.latency for a in answers if a.latency is not None]
        worst[name] = round(max(latencies) * 1000, 1) if latencies else None
        failed = [a for a in answers if a.latency is None]
        unanswered[name] = len(failed)
        if failed:
            why[name] = failed[0].error
    return worst, unanswered, why


def _sse_figures(soak: Soak, start: float, end: float) -> tuple[int, float]:
    sse = soak.cl.sse
    return sum(start <= t <= end for t, _ in sse.drops), sse.longest_silence(start, end)


#: gauges, and counters that grow with the steady load: not news in a phase's notes
NOT_NEWS = {"clients", "queued", "in_flight", "requests", "published", "connected",
            "commands", "connections"}


async def gateway_counters(soak: Soak) -> dict[str, float]:
    """The front ends' counters in /api/v1/health (``frontends``), flattened."""
    try:
        health = await h.http_json(soak.http_port, "/api/v1/health")
    except (OSError, TimeoutError, ValueError):
        return {}
    return {f"{end}.{key}": value for end, counts in health.get("frontends", {}).items()
            for key, value in counts.items()
            if isinstance(value, int | float) and not isinstance(value, bool)
            and key not in NOT_NEWS}


async def _fault(soak: Soak, phase: Phase, hold: float) -> Outcome:
    """The phase's fault, or, when its own clients do not end within ``PHASE_GRACE``
    of its hold, a problem that names it (the rig's, not the gateway's) rather than a
    soak that hangs until whoever runs it gives up."""
    fault: asyncio.Future[Outcome] = asyncio.ensure_future(phase.fault(soak, hold))
    done, _ = await asyncio.wait({fault}, timeout=hold + PHASE_GRACE)
    if done:
        return fault.result()
    fault.cancel()
    return Outcome(f"{phase.name}: did not end", [
        f"the phase's own clients did not end within {hold + PHASE_GRACE:.0f} s "
        "(the soak's, not the gateway's: its steady clients go on)"])


async def run_phase(soak: Soak, phase: Phase, hold: float, cycle: int) -> PhaseResult:
    counts0 = await soak.line_counts()
    counters0 = await gateway_counters(soak)
    rss0 = soak.samples[-1].rss_mb
    log0 = soak.gw.log_size()
    start = time.monotonic()
    outcome = await _fault(soak, phase, hold)
    ended = time.monotonic()
    recovery = await soak.until(lambda: phase.healthy(soak, ended), RECOVERY_TIMEOUT)
    end = time.monotonic()
    counts = await soak.line_counts() - counts0
    counted = {k: v - counters0.get(k, 0) for k, v in (await gateway_counters(soak)).items()
               if v != counters0.get(k, 0)}
    worst, unanswered, why = _window_figures(soak, start, end)
    drops, silence = _sse_figures(soak, start, end)
    problems = list(outcome.problems)
    if recovery is None:
        problems.append("the gateway died" if not soak.gw.alive() else
                        f"not healthy again {RECOVERY_TIMEOUT:.0f} s after the fault ended")
    for client, count in unanswered.items():
        if count and client not in phase.expect_down:
            problems.append(f"lost front end: the {client} client got no answer {count}x "
                            f"({why[client]})")
    if drops and "sse" not in phase.expect_down:
        problems.append(f"lost front end: the SSE stream of a client that reads was "
                        f"dropped {drops}x")
    log = soak.gw.log_since(log0)
    # the supervisor's line when a front end failed: it came back, but it fell over
    problems += [f"a front end failed and was restarted: {line.split(': ', 1)[-1]}"
                 for line in log.splitlines() if "; restarting it in" in line]
    rss = [s.rss_mb for s in soak.samples if start <= s.t <= end] or [rss0]
    gaps = sum(n for t, _, n in soak.cl.watcher.gaps if start <= t <= end)
    return PhaseResult(phase.name, cycle, start, end, round(hold, 1), recovery, worst,
                       unanswered, drops, round(silence, 2), gaps, counts["overlaps"],
                       counts["collisions"], round(max(rss) - rss0, 1), counted,
                       log.count("\n"), outcome.notes, problems, outcome.data)


@dataclass(frozen=True)
class Plan:
    """How long each part takes.  The warm-up is a tenth of the run (5-60 s); each
    fault or hostile client is held for the time left shared among the phases (2-20 s).
    Phases cycle in order until the time is used up; each runs at least once, so a very
    short run takes as long as one cycle of minimum holds (about a minute)."""

    seconds: float
    warmup: float
    hold: float

    @classmethod
    def of(cls, minutes: float, phases: int) -> Plan:
        seconds = minutes * 60
        warmup = min(max(0.1 * seconds, 5.0), 60.0)
        # a phase takes about 1.6 holds: its recovery and settling come on top
        hold = min(max((seconds - warmup) / (1.6 * phases), 2.0), 20.0)
        return cls(seconds, warmup, hold)


def progress(args: argparse.Namespace, text: str) -> None:
    if not args.quiet:
        print(f"soak: {text}", file=sys.stderr, flush=True)


async def run_phases(soak: Soak, phases: list[Phase], plan: Plan, deadline: float
                     ) -> tuple[list[PhaseResult], list[Sample]]:
    results: list[PhaseResult] = []
    quiet = [soak.samples[-1]]  # the warm-up's end, then after each phase
    cycle = 0
    while True:
        for phase in phases:
            if cycle and time.monotonic() + 1.6 * plan.hold > deadline:
                return results, quiet
            progress(soak.args, f"cycle {cycle + 1}: {phase.name} ({plan.hold:.1f} s)")
            result = await run_phase(soak, phase, plan.hold, cycle + 1)
            results.append(result)
            for problem in result.problems:
                progress(soak.args, f"  {phase.name}: {problem}")
            await asyncio.sleep(SETTLE)
            found = sample(soak.gw.pid)
            if found is None:
                progress(soak.args, "the gateway is gone: no further phases")
                return results, quiet
            quiet.append(found)
        cycle += 1


# ------------------------------------------------------------------ the verdicts


@dataclass(frozen=True)
class Trend:
    metric: str
    warm: float
    end: float
    rise: float  # median of the last quarter of the quiet samples minus the second's
    slope_per_min: float  # least squares over the second half
    tolerance: float
    leak: bool


TOLERANCE = {"rss_mb": 8.0, "fds": 8.0, "threads": 4.0}


def _slope(points: list[tuple[float, float]]) -> float:
    if len(points) < 2:
        return 0.0
    mean_t = statistics.fmean(t for t, _ in points)
    mean_v = statistics.fmean(v for _, v in points)
    spread = sum((t - mean_t) ** 2 for t, _ in points)
    if spread == 0:
        return 0.0
    return 60 * sum((t - mean_t) * (v - mean_v) for t, v in points) / spread


def trend(metric: str, quiet: list[Sample]) -> Trend:
    """Leak or not, from samples taken at quiet moments (after each phase has
    recovered and settled): those do not depend on which fault was on.  A leak is a
    rise beyond the tolerance from the second quarter of the run to the last."""
    values = [float(getattr(s, metric)) for s in quiet]
    n = len(values)
    second = values[n // 4: max(n // 2, n // 4 + 1)]
    last = values[-max(n // 4, 1):]
    rise = statistics.median(last) - statistics.median(second)
    half = [(s.t, v) for s, v in zip(quiet, values, strict=True)][n // 2:]
    tolerance = TOLERANCE[metric]
    return Trend(metric, values[0], values[-1], round(rise, 2), round(_slope(half), 3),
                 tolerance, rise > tolerance)


@dataclass
class Final:
    """What the soak saw at the end, and the shutdown."""

    alive: bool = False
    front_ends: dict[str, bool] = field(default_factory=dict)
    lines: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: each bus's requests written past their place next to a stream, as the gateway
    #: counted them (``late_writes``): a collision after one is the machine's holding
    late_writes: dict[str, int] = field(default_factory=dict)
    invented_in_log: int = 0
    exit_status: int | None = None
    log_tail: str = ""


async def final_checks(soak: Soak) -> Final:
    """Does each front end still answer (the steady clients are stopped by now, so the
    command asked here is the only one waiting for its result)?"""
    final = Final(alive=soak.gw.alive())
    record = soak.cl.mqtt.record
    before = len(record.answers)
    await soak.cl.mqtt.ask(time.monotonic())
    mqtt = record.answers[before].latency is not None
    final.front_ends = {"modbus": await modbus_ok(soak, 0.0), "http": await http_ok(soak, 0.0),
                        "mqtt": mqtt and await mqtt_ok(soak, 0.0)}
    with contextlib.suppress(OSError, TimeoutError, ValueError):
        final.late_writes = {bus["name"]: bus["late_writes"]
                             for bus in await h.http_json(soak.http_port, "/api/v1/buses")}
    return final


def incident_time(incident: list[str]) -> float:
    """When a simulator's incident happened: its last timed event is the incident."""
    return float(incident[-1].split()[0])


def during(results: list[PhaseResult], t: float) -> str:
    """The phase a moment fell in (the simulators and the soak share the monotonic
    clock)."""
    for r in results:
        if r.start <= t <= r.end:
            return f"{r.name} (cycle {r.cycle})"
    if not results or t < results[0].start:
        return "warm-up"
    return "after the last phase" if t > results[-1].end else "between phases"


def unasked_writes(lines: dict[str, dict[str, Any]], asked: Counter[tuple[str, str]]
                   ) -> tuple[dict[str, dict[str, int]], int]:
    """Writes the sensors heard that neither the soak nor a stream set-up asked for,
    and the stream stops among them (each one a stream the gateway invented)."""
    streams = {s.name for s in SENSORS if s.streams}
    unasked: dict[str, dict[str, int]] = {}
    stops = 0
    for stats in lines.values():
        for sensor, heard in stats.get("writes", {}).items():
            for write, count in heard.items():
                extra = count - asked[sensor, write]
                if (sensor in streams and write in STREAM_WRITES) or extra <= 0:
                    continue
                unasked.setdefault(sensor, {})[write] = extra
                stops += extra if write in STOP_WRITES else 0
    return unasked, stops


def failures(results: list[PhaseResult], trends: list[Trend], final: Final,
             asked: Counter[tuple[str, str]]) -> list[str]:
    """Every check that failed, one line each, named."""
    out = [f"{r.name} (cycle {r.cycle}): {p}" for r in results for p in r.problems]
    for name, stats in final.lines.items():
        if stats.get("collisions"):
            seen = sorted({during(results, incident_time(i)) for i in stats["incidents"]})
            out.append(f"collision: {stats['collisions']} on {name} (first ones during: "
                       f"{', '.join(seen)}; the gateway's late writes on it: "
                       f"{final.late_writes.get(name, 'unknown')})")
    unasked, stops = unasked_writes(final.lines, asked)
    if final.invented_in_log or stops:
        out.append(f"invented stream: {final.invented_in_log} in the gateway's log, "
                   f"{stops} stream stops sent to sensors that do not stream")
    if unasked:
        out.append(f"unasked writes (sent twice, or asked by no one): {unasked}")
    out += [f"leak trend: {t.metric} rose {t.rise:+g} (tolerance {t.tolerance:g})"
            for t in trends if t.leak]
    out += [f"lost front end at the end: {name}"
            for name, ok in final.front_ends.items() if not ok]
    if not final.alive:
        out.append("dead process: the gateway was not running at the end")
    elif final.exit_status != 0:
        out.append(f"unclean stop: SIGTERM ended the gateway with status {final.exit_status}")
    return out


# ------------------------------------------------------------------ the report


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def _silence(seconds: float) -> str:
    return "<0.1" if seconds < 0.1 else f"{seconds:.2f}"  # shorter ones are not noted


def phase_table(results: list[PhaseResult]) -> list[str]:
    rows = [f"{'phase':<20} {'cyc':>3} {'hold s':>6} {'recov s':>7} {'modbus ms':>9} "
            f"{'mqtt ms':>8} {'http ms':>8} {'sse gap s':>9} {'gaps':>4} {'coll':>4} "
            f"{'RSS +MB':>7}  result"]
    for r in results:
        recovery = "never" if r.recovery_s is None else f"{r.recovery_s:.2f}"
        rows.append(f"{r.name:<20} {r.cycle:>3} {r.hold_s:>6.1f} {recovery:>7} "
                    f"{_ms(r.worst_ms['modbus']):>9} {_ms(r.worst_ms['mqtt']):>8} "
                    f"{_ms(r.worst_ms['http']):>8} {_silence(r.sse_silence_s):>9} {r.mqtt_gaps:>4} "
                    f"{r.collisions:>4} {r.rss_rise_mb:>7.1f}  "
                    f"{'FAIL' if r.problems else 'ok'}")
        rows.append(f"{'':<20}     {r.notes}; gateway log +{r.log_lines} lines")
        if r.counted:
            rows.append(f"{'':<20}     gateway counted: " + ", ".join(
                f"{k} {v:+g}" for k, v in sorted(r.counted.items())))
        rows += [f"{'':<20}     FAIL: {p}" for p in r.problems]
    return rows


def resource_table(trends: list[Trend]) -> list[str]:
    rows = [f"{'resource':<10} {'warm-up end':>11} {'end':>8} {'rise Q2->Q4':>11} "
            f"{'slope/min':>9} {'tolerance':>9}  verdict"]
    rows += [f"{t.metric:<10} {t.warm:>11.1f} {t.end:>8.1f} {t.rise:>+11.1f} "
             f"{t.slope_per_min:>+9.2f} {t.tolerance:>9g}  {'LEAK' if t.leak else 'ok'}"
             for t in trends]
    return rows


def summary_lines(summary: dict[str, Any]) -> list[str]:
    final, sse, mqtt = summary["final"], summary["sse"], summary["mqtt"]
    out = [f"imu-gateway soak: {summary['minutes_run']:.1f} min; {summary['run']}", "",
           *phase_table([PhaseResult(**r) for r in summary["phases"]]), "",
           *resource_table([Trend(**t) for t in summary["trends"]]), ""]
    for name, stats in final["lines"].items():
        out.append(f"simulator {name}: overlaps {stats.get('overlaps')}, collisions "
                   f"{stats.get('collisions')}, noise bytes {stats.get('noise_bytes')}; "
                   f"held by the machine {stats.get('holds')} times ({stats.get('held_s')} s), "
                   f"its pty late {stats.get('lags')} times ({stats.get('lagged_s')} s), "
                   f"{stats.get('after_holds')} overlaps and collisions right after "
                   "(not counted); the gateway's writes too late to end before a "
                   f"stream's frame {final.get('late_writes', {}).get(name, 'unknown')}")
        for incident in stats.get("incidents", [])[:1]:  # what led to the first one
            out += [f"    {event[:100]}" for event in incident[-5:]]
    unasked, stops = summary["unasked_writes"], summary["stream_stops_unasked"]
    out += [f"invented streams: {final['invented_in_log']} in the gateway's log, {stops} stream "
            f"stops to sensors that do not stream; unasked writes: {unasked or 'none'}",
            f"MQTT: {mqtt['states']} states, sequence gaps {mqtt['gaps']} "
            f"({mqtt['gaps_in_broker_restarts']} of them while the broker restarted)",
            f"SSE: {sse['events']} events, {sse['drops']} drops, {sse['gaps']} sequence gaps",
            f"Modbus TCP writer (zero type to a1, never to be sent twice): "
            f"{summary['writer']}",
            "front ends at the end: " + ", ".join(
                f"{n} {'answers' if ok else 'LOST'}" for n, ok in final["front_ends"].items())
            + f"; gateway {'alive' if final['alive'] else 'DEAD'}, "
            f"stopped with status {final['exit_status']}", ""]
    if summary["failures"]:
        out += ["RESULT: FAIL", *(f"  - {f}" for f in summary["failures"])]
    else:
        out.append("RESULT: PASS")
    return out


def build_summary(soak: Soak, plan: Plan, results: list[PhaseResult], trends: list[Trend],
                  final: Final, minutes_run: float) -> dict[str, Any]:
    watcher, sse = soak.cl.watcher, soak.cl.sse
    restarts = [(r.name, r) for r in results if r.name == "broker-restart"]
    unasked, stops = unasked_writes(final.lines, soak.asked)
    priority = f"SCHED_FIFO {GATEWAY_PRIORITY}" if soak.realtime else "normal priority"
    return {
        "run": f"{len(results)} phases run in {max((r.cycle for r in results), default=0)} "
               f"cycle(s), hold {plan.hold:.1f} s, warm-up {plan.warmup:.0f} s; "
               f"gateway at {priority}, simulators at SCHED_FIFO {SIM_PRIORITY} where allowed",
        "minutes_asked": plan.seconds / 60, "minutes_run": minutes_run,
        "phases": [asdict(r) for r in results], "trends": [asdict(t) for t in trends],
        "final": asdict(final), "unasked_writes": unasked, "stream_stops_unasked": stops,
        "mqtt": {"states": watcher.states, "gaps": sum(n for _, _, n in watcher.gaps),
                 "gaps_in_broker_restarts": sum(r.mqtt_gaps for _, r in restarts)},
        "sse": {"events": sse.events, "drops": len(sse.drops),
                "gaps": sum(n for _, _, n in sse.gaps)},
        # more than 1: the poller's one connection was lost at least once
        "modbus_poller_connections": soak.cl.modbus.reconnects,
        "writer": soak.cl.writer.outcomes,
        "samples": [asdict(s) for s in soak.samples],
        "failures": failures(results, trends, final, soak.asked),
    }


# ------------------------------------------------------------------ main


async def soak_run(soak: Soak, phases: list[Phase], plan: Plan) -> dict[str, Any]:
    started = time.monotonic()
    await asyncio.to_thread(soak.start_processes)
    progress(soak.args, f"gateway pid {soak.gw.pid}; files in {soak.folder}")
    await soak.start_clients()
    progress(soak.args, f"warm-up {plan.warmup:.0f} s")
    await asyncio.sleep(plan.warmup)
    results, quiet = await run_phases(soak, phases, plan, started + plan.seconds)
    trends = [trend(metric, quiet) for metric in TOLERANCE]
    await soak.stop_clients()
    final = await final_checks(soak)
    await asyncio.to_thread(soak.stop_processes)
    final.exit_status = soak.gw.exit_status
    final.lines = {name: line.stop() for name, line in soak.lines.items()}
    log = soak.gw.log_since(0)
    final.invented_in_log = log.count("streams though stream_hz is 0")
    final.log_tail = "\n".join(log.splitlines()[-20:])
    summary = build_summary(soak, plan, results, trends, final,
                            (time.monotonic() - started) / 60)
    summary["phases_planned"] = [p.name for p in phases]
    return summary


class WorkFolder:
    """The config, the logs and the pty links: ``--keep DIR``, or a temporary folder
    that is removed after a run that passed and kept (and named) otherwise."""

    def __init__(self, keep: str | None) -> None:
        self.kept = keep is not None
        self.path = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="soak-"))
        self.path.mkdir(parents=True, exist_ok=True)

    def done(self, passed: bool) -> None:
        if passed and not self.kept:
            shutil.rmtree(self.path, ignore_errors=True)
        else:
            print(f"soak: the gateway's config and log are in {self.path}", file=sys.stderr)


def raise_fd_limit() -> None:
    """600 hostile connections and the clients beside them need more descriptors than
    a login shell's usual 1024, here and in the gateway (which inherits the limit)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    wanted = 65536 if hard == resource.RLIM_INFINITY else min(hard, 65536)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0,
                        help="how long (default 10); every phase runs at least once")
    parser.add_argument("--json", metavar="PATH", help="also write the summary as JSON")
    parser.add_argument("--only", metavar="PHASE,...",
                        help=f"run only these phases: {', '.join(p.name for p in PHASES)}")
    parser.add_argument("--keep", metavar="DIR",
                        help="put the config and logs in DIR and keep them")
    parser.add_argument("--gateway-priority", choices=["realtime", "normal"],
                        default="realtime", help="realtime (default, as the systemd unit "
                        "runs it; normal where not allowed) or normal")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    phases = list(PHASES)
    if args.only:
        wanted = set(args.only.split(","))
        phases = [p for p in PHASES if p.name in wanted]
        if unknown := wanted - {p.name for p in phases}:
            print(f"soak: unknown phase(s): {', '.join(sorted(unknown))}", file=sys.stderr)
            return 2
    raise_fd_limit()
    plan = Plan.of(args.minutes, len(phases))
    folder = WorkFolder(args.keep)
    soak = Soak(folder.path, args)
    try:
        summary = asyncio.run(soak_run(soak, phases, plan))
    except (RuntimeError, OSError) as exc:
        print(f"soak: could not run: {exc}", file=sys.stderr)
        folder.done(passed=False)
        return 2
    finally:
        soak.stop_processes()
    print("\n".join(summary_lines(summary)), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=1) + "\n")
    folder.done(passed=not summary["failures"])
    return 1 if summary["failures"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
