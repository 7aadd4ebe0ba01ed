"""The gateway on a busy machine: does it keep the bus's rules when the CPU is taken?

Beside it run ``--burners`` processes that spin (CPU burners, like ``stress-ng --cpu``)
and ``--chatty`` processes that wake a few thousand times a second, so the
scheduler is busy as well as the cores.  Each line's simulated sensors run in a
process of their own (like real sensors, they share no interpreter with the gateway),
the gateway in its own (``imu-gateway run``), on three lines:

* ``slow``: native at 115200, two AH and a VG answering 5-40 ms late (jittered), all
  polled flat out;
* ``modbus``: Modbus RTU at 115200, two AH answering 5-40 ms late, flat out;
* ``stream``: native at 460800, a MINS streaming at 100 Hz and an AH polled at 10 Hz
  between its frames.

Printed at the end, per sensor: readings, offline events, late answers and learned
timeout, and what the simulator saw: overlaps (a request sent while a sensor was
answering), collisions (two senders at once) and writes nobody asked for (anything
but the stream set-up of the streaming MINS).  Exit 1 if any rule was broken: a live
sensor reported offline, a stream invented, a write unasked, an overlap or a
collision.

A simulator plays hardware, which never stops; but on a virtual machine the host
takes the CPUs away now and then (steal time: 40-750 ms holds were seen here, even of
a SCHED_FIFO 99 process).  A simulator held that long reads the requests of that time
late and misses its stream's beat, so the overlaps and collisions within half a
second of a hold are its doing, not the gateway's: they are shown, and not counted.

Run: ``.venv/bin/python bench/busy.py [--seconds 60] [--burners 4] [--chatty 2]``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common import free_port

BURN = "while True: pass"
CHATTY = "import time\nwhile True:\n    time.sleep(0.0003)\n    sum(range(300))"
STREAM_SETUP = {"set_output_type", "set_output_rate"}
#: The simulators play hardware, and real sensors do not share the gateway's CPU: they
#: run with real-time priority where this machine allows it (root and chrt), above the
#: gateway's own when that is real-time too (a process of equal SCHED_FIFO priority is
#: never preempted, so a busy gateway thread would hold a "sensor" off its core), so that
#: what is measured is the gateway's behaviour, not a starved simulator's lateness.
CAN_CHRT = shutil.which("chrt") is not None and os.geteuid() == 0
SIM_PRIORITY, GATEWAY_PRIORITY = 20, 10  # SCHED_FIFO, as scripts/soak runs them
REALTIME = ["chrt", "--fifo", str(SIM_PRIORITY)] if CAN_CHRT else []
GATEWAY_REALTIME = ["chrt", "--fifo", str(GATEWAY_PRIORITY)] if CAN_CHRT else []


@dataclass(frozen=True)
class Line:
    baud: int
    protocol: str
    simulate: tuple[str, ...]  # the simulator's options besides --sensor
    sensors: tuple[tuple[str, str, int, str], ...]  # name, series, address, config extra


LINES = {
    "slow": Line(115200, "native", ("--answer-delay-ms", "5", "--jitter-ms", "35"), (
        ("n1", "AH", 1, "poll_hz: 0"), ("n2", "AH", 2, "poll_hz: 0"),
        ("n3", "VG", 3, "poll_hz: 0"))),
    "modbus": Line(115200, "modbus", ("--answer-delay-ms", "5", "--jitter-ms", "35"), (
        ("m1", "AH", 1, "poll_hz: 0"), ("m2", "AH", 2, "poll_hz: 0"))),
    "stream": Line(460800, "native", (), (
        ("s1", "MINS", 1, "stream_hz: 100"), ("s2", "AH", 2, "poll_hz: 10"))),
}


@contextlib.contextmanager
def simulator(line: Line, seed: int) -> Iterator[tuple[str, subprocess.Popen[str]]]:
    """``imu-gateway simulate`` for one line, in a process of its own."""
    args = [*REALTIME, sys.executable, "-m", "imu_gateway", "simulate", "--seed", str(seed),
            *line.simulate]
    for _, series, address, _ in line.sensors:
        args += ["--sensor", f"{line.protocol}:{series}:{address}:{line.baud}"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    try:
        yield proc.stdout.readline().split()[1], proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait(30)


def stopped(proc: subprocess.Popen[str]) -> dict[str, Any]:
    """Stop a simulator; what it says it saw."""
    proc.terminate()
    _, err = proc.communicate(timeout=30)
    line = next(x for x in err.splitlines() if x.startswith("simulate: stopped: "))
    summary: dict[str, Any] = json.loads(line.removeprefix("simulate: stopped: "))
    return summary


@contextlib.contextmanager
def load(burners: int, chatty: int) -> Iterator[None]:
    procs = [subprocess.Popen([sys.executable, "-c", code])
             for code in [BURN] * burners + [CHATTY] * chatty]
    try:
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def get(port: int, path: str) -> Any:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=30) as answer:
        return json.loads(answer.read())


def buses_yaml(lines: dict[str, Line], ports: dict[str, str]) -> str:
    """The config's ``buses:``, one line of YAML a bus."""
    out = "buses:\n"
    for name, line in lines.items():
        sensors = ", ".join(f"{{name: {n}, series: {series}, address: {a}, {extra}}}"
                            for n, series, a, extra in line.sensors)
        out += (f"  - {{name: {name}, port: {ports[name]}, baudrate: {line.baud}, "
                f"protocol: {line.protocol}, sensors: [{sensors}]}}\n")
    return out


def config_yaml(ports: dict[str, str], http: int) -> str:
    return buses_yaml(LINES, ports) + f"http: {{listen: '127.0.0.1:{http}'}}\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--burners", type=int, default=4)
    parser.add_argument("--chatty", type=int, default=2)
    parser.add_argument("--gateway-realtime", action="store_true",
                        help="run the gateway at real-time priority too (as systemd's "
                        "CPUSchedulingPolicy=fifo would)")
    parser.add_argument("-v", "--verbose", action="store_true",
                        help="print the first overlaps and collisions with what led to them")
    args = parser.parse_args()
    with contextlib.ExitStack() as stack, tempfile.TemporaryDirectory() as tmp:
        sims = {name: stack.enter_context(simulator(line, seed))
                for seed, (name, line) in enumerate(LINES.items())}
        http = free_port()
        config = Path(tmp) / "busy.yaml"
        config.write_text(config_yaml({n: port for n, (port, _) in sims.items()}, http))
        log = Path(tmp) / "gateway.log"
        stack.enter_context(load(args.burners, args.chatty))
        with log.open("w") as out:
            gateway = subprocess.Popen([*(GATEWAY_REALTIME if args.gateway_realtime else []),
                                        sys.executable, "-m", "imu_gateway", "run", "-c",
                                        str(config)], stderr=out)
            try:
                time.sleep(args.seconds)  # the measurement's length, not a wait for an event
                sensors, buses = get(http, "/api/v1/sensors"), get(http, "/api/v1/buses")
            finally:
                gateway.terminate()
                gateway.wait(30)
        seen = {name: stopped(proc) for name, (_, proc) in sims.items()}
        return report(seen, sensors, buses, log.read_text(), args)


def report(seen: dict[str, dict[str, Any]], sensors: list[dict[str, Any]],
           buses: list[dict[str, Any]], log: str, args: argparse.Namespace) -> int:
    timing = {n: t for b in buses for n, t in b["timing"].items()}
    readings = {s["name"]: s["seq"] for s in sensors}
    sims = f"at SCHED_FIFO {SIM_PRIORITY}" if REALTIME else "at normal priority"
    gateway = f", gateway at SCHED_FIFO {GATEWAY_PRIORITY}" \
        if args.gateway_realtime and REALTIME else ""
    print(f"{args.seconds:g} s, {args.burners} CPU burners, {args.chatty} chatty processes; "
          f"simulators {sims}{gateway}")
    print(f"{'sensor':6} {'line':7} {'readings':>8} {'offline':>7} {'late':>5} "
          f"{'latency ms':>10} {'timeout ms':>10} {'unasked writes':>14}")
    broken = 0
    for line_name, line in LINES.items():
        writes = list(seen[line_name]["writes_heard"].values())
        for (name, _, _, extra), heard in zip(line.sensors, writes, strict=True):
            unasked = {k: v for k, v in heard.items()
                       if not (extra.startswith("stream_hz") and k in STREAM_SETUP)}
            offline = sum(f"sensor {name}: offline" in row for row in log.splitlines())
            t = timing[name]
            print(f"{name:6} {line_name:7} {readings[name]:8} {offline:7} "
                  f"{t['late_answers']:5} {t['latency_ms'] or 0:10.1f} {t['timeout_ms']:10.1f} "
                  f"{sum(unasked.values()):14}")
            broken += offline + sum(unasked.values()) + (readings[name] == 0)
    for line_name, stats in seen.items():
        held = stats["overlaps_after_hold"] + stats["collisions_after_hold"]
        print(f"line {line_name}: overlaps {stats['overlaps'] - stats['overlaps_after_hold']}, "
              f"collisions {stats['collisions'] - stats['collisions_after_hold']}; "
              f"simulator held {stats['holds']} times ({stats['held_s']:.2f} s in all), "
              f"with {held} overlaps and collisions right after (not counted)")
        broken += stats["overlaps"] + stats["collisions"] - held
        for incident in stats["incidents"][:3] if args.verbose else []:
            print("   ", " | ".join(incident))
    invented = log.count("streams though stream_hz is 0")
    print(f"streams invented: {invented}")
    broken += invented
    print("rules kept" if not broken else f"RULES BROKEN ({broken})")
    return 0 if not broken else 1


if __name__ == "__main__":
    raise SystemExit(main())
