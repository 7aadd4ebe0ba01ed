"""The gateway on an edge box: does a quarter of one core suffice?

A slow ARM core shared with other work (a Raspberry Pi, a Moxa UC, a Siemens IOT2050)
is played by a cpu cgroup limited to 25 % of one core (cgroup v1
``cpu.cfs_quota_us=2500`` and ``cpu.cfs_period_us=10000``, or v2 ``cpu.max "2500
10000"``).  The gateway (``imu-gateway run``, a process of its own at normal priority:
CFS quotas do not hold real-time threads) carries:

* ``native``: native at 460800, an AH polled flat out and a MINS streaming at 100 Hz
  (not 115200: there the MINS's 48-byte frames leave pauses of 5.8 ms, and an AH's
  exchange, 57 bytes of answer 2 ms late, takes 7.4; no poll fits a pause, and each
  would meet the stream's next frame);
* ``modbus``: Modbus RTU at 115200, a VG and an AH polled flat out;

with every front end on: Modbus TCP, MQTT with Home Assistant discovery (a real
mosquitto, a subscriber on every state), REST with what the dashboard asks (its
stream and its polling), OPC UA with one subscription; and, as clients, 10 Modbus TCP
pollers (10 requests a second each) and one more SSE client.  The simulators and the
clients run outside the cgroup (they stand for hardware and for other machines).

The gateway is moved into the cgroup and out again: free, quarter, free, quarter, …
(``--rounds``), each phase ``--seconds`` long after a short settle, so the two are
measured in the same run.  Printed: each line's exchanges per second and the 100 Hz
stream's samples per second in each, their ratio (the goal: ≥ 0.8), the gateway's CPU
(cores), the REST health's slowest answer (the goal: within 1 s); and, over the whole
run, collisions and overlaps on the lines, streams invented, live sensors reported
offline.  Exit 1 when a goal is missed or a rule broken, 2 when the cgroup cannot be
made (not root, no cpu controller): the message says why.

Run: ``.venv/bin/python bench/edge.py [--seconds 20] [--rounds 2] [--hand-over-ms 20]``
(``--hand-over-ms``: the gateway's ``hand_over_ms``, docs/deployment.md).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import hostile as h
from busy import Line, buses_yaml, simulator, stopped
from common import free_port
from soak import GatewayProcess, QuietMosquitto, favour
from support.broker import Mosquitto

QUOTA_US, PERIOD_US = 2500, 10000
GOAL_RATE, GOAL_HEALTH_S = 0.8, 1.0
STREAM = "mins"
LINES = {
    "native": Line(460800, "native", ("--answer-delay-ms", "2"), (
        ("ah", "AH", 1, "poll_hz: 0"), (STREAM, "MINS", 2, "stream_hz: 100"))),
    "modbus": Line(115200, "modbus", ("--answer-delay-ms", "2"), (
        ("vg", "VG", 1, "poll_hz: 0"), ("mah", "AH", 2, "poll_hz: 0"))),
}
SENSORS = [s[0] for line in LINES.values() for s in line.sensors]
POLLERS = 10
SETTLE_S = 3.0  # after a move: the learned timeouts and the queues find their level


class CgroupUnavailable(Exception):
    """The cgroup cannot be made here; the message says why."""


class QuarterCore:
    """A cpu cgroup limited to QUOTA_US per PERIOD_US, into which a process (every
    thread of it) is moved and out of which it is moved back."""

    def __init__(self) -> None:
        name = f"imu-edge-{os.getpid()}"
        v2 = Path("/sys/fs/cgroup")
        v1 = Path("/sys/fs/cgroup/cpu")
        try:
            if "cpu" in (v2 / "cgroup.controllers").read_text().split() \
                    if (v2 / "cgroup.controllers").exists() else False:
                (v2 / "cgroup.subtree_control").write_text("+cpu")
                self.home, self.path = v2, v2 / name
                self.path.mkdir()
                (self.path / "cpu.max").write_text(f"{QUOTA_US} {PERIOD_US}")
            elif (v1 / "cpu.cfs_quota_us").exists():
                self.home, self.path = v1, v1 / name
                self.path.mkdir()
                # the period first: a quota longer than the period it replaces is refused
                (self.path / "cpu.cfs_period_us").write_text(str(PERIOD_US))
                (self.path / "cpu.cfs_quota_us").write_text(str(QUOTA_US))
            else:
                raise CgroupUnavailable("no cpu controller: neither cgroup v2's cpu.max "
                                        "nor v1's /sys/fs/cgroup/cpu is there")
        except PermissionError as exc:
            raise CgroupUnavailable(f"no permission to make a cgroup ({exc}); run as root, "
                                    "or with a delegated cgroup (systemd-run --user "
                                    "--scope -p Delegate=yes)") from exc
        except OSError as exc:
            raise CgroupUnavailable(f"the cgroup could not be made: {exc}") from exc

    def describe(self) -> str:
        return f"{self.path} ({QUOTA_US} µs of CPU per {PERIOD_US} µs)"

    def join(self, pid: int) -> None:
        (self.path / "cgroup.procs").write_text(str(pid))

    def leave(self, pid: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            (self.home / "cgroup.procs").write_text(str(pid))

    def remove(self) -> None:
        with contextlib.suppress(OSError):
            self.path.rmdir()


def cpu_seconds(pid: int) -> float:
    """The process's user and system time, every thread."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True)
class Counts:
    at: float
    cpu: float
    transactions: dict[str, int]  # per bus
    seq: dict[str, int]  # per sensor
    late_writes: int  # all buses': requests written too late to end before a stream frame


@dataclass
class Phase:
    quarter: bool
    start: Counts
    end: Counts
    health_s: float  # the slowest health answer
    offline: int  # "offline" log lines of the phase

    def rate(self, bus: str) -> float:
        return (self.end.transactions[bus] - self.start.transactions[bus]) / self.seconds

    def stream(self) -> float:
        return (self.end.seq[STREAM] - self.start.seq[STREAM]) / self.seconds

    def cores(self) -> float:
        return (self.end.cpu - self.start.cpu) / self.seconds

    @property
    def seconds(self) -> float:
        return self.end.at - self.start.at


@dataclass
class Health:
    """The REST health, asked twice a second; the slowest answer since ``reset``."""

    port: int
    slowest: float = 0.0
    failures: list[str] = field(default_factory=list)

    def reset(self) -> None:
        self.slowest = 0.0

    async def run(self) -> None:
        while True:
            at = time.monotonic()
            try:
                await h.http_get(self.port, "/api/v1/health", timeout=10)
            except (OSError, TimeoutError) as exc:
                self.failures.append(repr(exc))
            self.slowest = max(self.slowest, time.monotonic() - at)
            await asyncio.sleep(max(0.0, at + 0.5 - time.monotonic()))


def config_yaml(ports: dict[str, str], modbus: int, http: int, mqtt: int, opcua: int,
                pki: Path, hand_over_ms: int = 0) -> str:
    return (f"gateway_id: edge\nhand_over_ms: {hand_over_ms}\n" + buses_yaml(LINES, ports)
            + f"modbus: {{listen: '127.0.0.1:{modbus}'}}\n"
            f"mqtt: {{url: 'mqtt://127.0.0.1:{mqtt}', homeassistant_discovery: true}}\n"
            f"http: {{listen: '127.0.0.1:{http}'}}\n"
            f"opcua: {{listen: '127.0.0.1:{opcua}', allow_none: true, pki_dir: '{pki}'}}\n")


async def counts(http: int, pid: int) -> Counts:
    buses = await h.http_json(http, "/api/v1/buses")
    sensors = await h.http_json(http, "/api/v1/sensors")
    return Counts(time.monotonic(), cpu_seconds(pid),
                  {b["name"]: b["transactions"] for b in buses},
                  {s["name"]: s["seq"] for s in sensors},
                  sum(b["late_writes"] for b in buses))


async def opcua_subscriber(port: int, stop: asyncio.Event) -> int:
    """One OPC UA client, one subscription (100 ms) on every sensor's pitch and roll:
    the data changes it was sent."""
    from asyncua import Client

    class Handler:
        changes = 0

        def datachange_notification(self, *_: object) -> None:
            Handler.changes += 1

    async with Client(f"opc.tcp://127.0.0.1:{port}/") as client:
        ns = await client.get_namespace_index("urn:imu-gateway")
        nodes = [client.get_node(f"ns={ns};s=edge.Sensors.{s}.Angles.{f}")
                 for s in SENSORS for f in ("pitch", "roll")]
        subscription = await client.create_subscription(100, Handler())
        await subscription.subscribe_data_change(nodes)
        await stop.wait()
    return Handler.changes


def offline_lines(log: str) -> int:
    return sum(f"sensor {name}: offline" in row for row in log.splitlines()
               for name in SENSORS)


async def measure(args: argparse.Namespace, gateway: GatewayProcess, http: int,
                  group: QuarterCore, health: Health) -> list[Phase]:
    phases: list[Phase] = []
    for quarter in [False, True] * args.rounds:
        (group.join if quarter else group.leave)(gateway.pid)
        await asyncio.sleep(SETTLE_S)  # the settle, not a wait for an event
        log0, start = gateway.log_size(), await counts(http, gateway.pid)
        health.reset()
        await asyncio.sleep(args.seconds)  # the measurement's length
        end = await counts(http, gateway.pid)
        phases.append(Phase(quarter, start, end, health.slowest,
                            offline_lines(gateway.log_since(log0))))
        print(f"  {'quarter' if quarter else 'free':7} (from {start.at:.1f}): "
              + ", ".join(f"{b} {phases[-1].rate(b):.1f} tx/s" for b in LINES)
              + f", {STREAM} {phases[-1].stream():.1f}/s, {phases[-1].cores():.3f} cores, "
              f"health ≤ {phases[-1].health_s * 1000:.0f} ms, "
              f"late writes {end.late_writes - start.late_writes}", flush=True)
    group.leave(gateway.pid)
    return phases


async def run(args: argparse.Namespace, group: QuarterCore) -> int:
    with contextlib.ExitStack() as stack, tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        sims = {name: stack.enter_context(simulator(line, seed))
                for seed, (name, line) in enumerate(LINES.items())}
        broker: Mosquitto = QuietMosquitto(folder)
        broker.start()
        stack.callback(broker.stop)
        modbus, http, opcua = free_port(), free_port(), free_port()
        config = folder / "edge.yaml"
        config.write_text(config_yaml({n: port for n, (port, _) in sims.items()}, modbus,
                                      http, broker.port, opcua, folder / "pki",
                                      args.hand_over_ms))
        gateway = GatewayProcess(config, folder / "gateway.log", realtime=False)
        stack.callback(gateway.stop)
        favour()  # the clients stand for other machines: the load is the gateway's
        outcome = await with_clients(args, gateway, group, modbus, http, broker.port, opcua)
        gateway.stop()
        seen = {name: stopped(proc) for name, (_, proc) in sims.items()}
        if args.log:
            Path(args.log).write_text(gateway.log_since(0))
        return report(args, outcome, seen, gateway.log_since(0))


@dataclass(frozen=True)
class Outcome:
    phases: list[Phase]
    health_failures: list[str]
    opcua_changes: int
    sse_events: int
    mqtt_states: int
    modbus_failures: int


async def with_clients(args: argparse.Namespace, gateway: GatewayProcess, group: QuarterCore,
                       modbus: int, http: int, mqtt: int, opcua: int) -> Outcome:
    deadline = time.monotonic() + 60
    while not await h.modbus_once(modbus) or not all(
            s["seq"] for s in await h.http_json(http, "/api/v1/sensors")):
        if not gateway.alive() or time.monotonic() > deadline:
            raise RuntimeError("the gateway did not come up:\n" + gateway.log_since(0)[-2000:])
        await asyncio.sleep(0.2)
    units = list(range(1, len(SENSORS) + 1))
    pollers = [h.ModbusPoller(modbus, units) for _ in range(POLLERS)]
    dashboard = h.HttpPoller(http, SENSORS, period=2.0)
    streams = [h.SseReader(http), h.SseReader(http)]  # the dashboard's and one more
    watcher = h.MqttWatcher(mqtt, "imu/edge")
    health, stop = Health(http), asyncio.Event()
    tasks = [asyncio.create_task(run()) for run in (
        *(p.run for p in pollers), dashboard.run, *(s.run for s in streams), health.run)]
    opcua_task = asyncio.create_task(opcua_subscriber(opcua, stop))
    try:
        phases = await measure(args, gateway, http, group, health)
    finally:
        stop.set()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        watcher.close()
    return Outcome(phases, health.failures, await opcua_task,
                   sum(s.events for s in streams), watcher.states,
                   sum(1 for p in pollers for a in p.record.answers if a.latency is None))


def report(args: argparse.Namespace, outcome: Outcome, seen: dict[str, dict[str, object]],
           log: str) -> int:
    free = [p for p in outcome.phases if not p.quarter]
    quarter = [p for p in outcome.phases if p.quarter]

    def ratio(figure: str) -> float:
        def mean(phases: list[Phase]) -> float:
            return sum(p.rate(figure) if figure in LINES else p.stream()
                       for p in phases) / len(phases)
        return mean(quarter) / mean(free)

    broken: list[str] = []
    print(f"\n{QUOTA_US} µs per {PERIOD_US} µs, {args.rounds} rounds of {args.seconds:g} s; "
          f"gateway CPU free {sum(p.cores() for p in free) / len(free):.3f} cores, "
          f"quarter {sum(p.cores() for p in quarter) / len(quarter):.3f}")
    for figure in (*LINES, STREAM):
        value = ratio(figure)
        print(f"{figure:8} quarter/free {value:.3f} (goal ≥ {GOAL_RATE})")
        if value < GOAL_RATE:
            broken.append(f"{figure} kept {value:.3f} of its rate")
    slowest = max(p.health_s for p in outcome.phases)
    print(f"health: slowest answer {slowest * 1000:.0f} ms (goal ≤ {GOAL_HEALTH_S * 1000:.0f}),"
          f" {len(outcome.health_failures)} failed")
    if slowest > GOAL_HEALTH_S or outcome.health_failures:
        broken.append("health answered late or not at all")
    print(f"clients: OPC UA data changes {outcome.opcua_changes}, SSE events "
          f"{outcome.sse_events}, MQTT states {outcome.mqtt_states}, Modbus TCP failures "
          f"{outcome.modbus_failures}")
    broken += rules(seen, log, outcome, args.verbose)
    print("goals met, rules kept" if not broken else "MISSED: " + "; ".join(broken))
    return 0 if not broken else 1


def rules(seen: dict[str, dict[str, object]], log: str, outcome: Outcome,
          verbose: bool) -> list[str]:
    broken = []
    for name, stats in seen.items():
        bad = int(str(stats["overlaps"])) + int(str(stats["collisions"]))
        held = int(str(stats["overlaps_after_hold"])) + int(str(stats["collisions_after_hold"]))
        print(f"line {name}: overlaps {stats['overlaps']}, collisions {stats['collisions']} "
              f"({held} right after the simulator was held, not counted)")
        if bad - held:
            broken.append(f"line {name}: {bad - held} overlaps and collisions")
        incidents = stats["incidents"]
        assert isinstance(incidents, list)
        for incident in incidents[:3] if verbose else []:
            print("   ", " | ".join(incident[-6:]))
    invented = log.count("streams though stream_hz is 0")
    offline = sum(p.offline for p in outcome.phases)
    print(f"streams invented: {invented}; live sensors reported offline: {offline}")
    if invented or offline:
        broken.append(f"{invented} streams invented, {offline} offline reports")
    return broken


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--log", help="keep the gateway's log in this file")
    parser.add_argument("--hand-over-ms", type=int, default=0,
                        help="the gateway's hand_over_ms (docs/deployment.md)")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="print the first overlaps and collisions with what led to them")
    args = parser.parse_args()
    try:
        group = QuarterCore()
    except CgroupUnavailable as exc:
        print(f"edge: cannot run: {exc}", file=sys.stderr)
        return 2
    print(f"cgroup {group.describe()}; {os.cpu_count()} CPUs", flush=True)
    try:
        return asyncio.run(run(args, group))
    finally:
        group.remove()


if __name__ == "__main__":
    raise SystemExit(main())
