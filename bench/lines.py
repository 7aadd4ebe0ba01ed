"""Many lines in one gateway: 1, 2, 4 and 8 lines at 115200 baud, flat out.

Each line has one simulated AH (``poll_hz: 0``) in a simulator process of its own (as
real sensors, they share no interpreter with the gateway; on a 2-core machine the
eight simulators compete with the gateway for the CPU, as a plant's other work would).
One gateway carries all the lines.  Printed per protocol and line count:

* each line's utilisation (time in an exchange ÷ elapsed), the lowest and highest;
* the lowest against the single-line utilisation measured in the same run (the goal:
  ≥ 0.9);
* the gateway's CPU per exchange (the process's CPU time ÷ exchanges, every thread);
* with one line, that CPU against its target (issue 29: a native line 0.2 ms, a Modbus
  line 0.3 ms; at most 1.0 meets it), next to the bare loop's of the same run: on a
  slow ARM core in a quarter-core cgroup a line above its target is throttled; and
  the times the gateway and the bare loop slept and were woken per exchange;
* a bare reference measured in the same run against the same simulators: one thread,
  one ``select()`` over every line, each request written when the answer before it is
  in, a half-in answer left alone until its rest could be in, as the gateway does (no
  schedule, no decoding, no cache, no checks): its exchanges per second per line and its
  CPU per exchange.  It shows what the simulators allow and what Python's least work
  per exchange costs on this machine.

Run: ``.venv/bin/python bench/lines.py [--seconds 5] [--lines 1 --lines 8]
[--protocol native] [--capture]`` (``--capture``: with event capture's rings filled).

``--warm``: instead, the bus path alone, warm: a ``BusMaster`` on a link that takes
each request and is handed the sensor's answer at once (the answer made once by the
simulator's sensor, then reused), on a clock of its own, in one thread, with nothing
between two exchanges.  Its µs per exchange is the Python work of an exchange (schedule,
framing, decoding, the reading, the hand-over's batch); the real line's CPU per
exchange, less the bare loop's, less this, is what running cold costs: the caches
emptied by the 8 ms between two exchanges, the thread's wake-ups.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import resource
import select
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import serial
from bus import Case, start_simulator

from imu_gateway.app import GIL_SWITCH_INTERVAL, Gateway
from imu_gateway.bus import master as bus_master
from imu_gateway.bus.link import SerialLink
from imu_gateway.config import config_from_dict
from imu_gateway.model import KnownSettings, Reading, Series, WireProtocol
from imu_gateway.protocol.exchanges import ModbusAdapter, NativeAdapter, rtu_silence
from imu_gateway.simulator import make_sensor
from imu_gateway.stats import BusStats, SensorStats

BAUD = 115200
DELAY = 0.002  # the simulated sensors' answer delay, s
#: The CPU one line may cost per exchange (s), by protocol: one line must fit a quarter
#: of a slow core (docs/benchmarks.md, "CPU per exchange on one line").
CPU_TARGET = {"native": 0.0002, "modbus": 0.0003}


@dataclass(frozen=True)
class Figures:
    per_line_tps: list[float]
    utilisation: list[float]
    cpu_per_exchange: float  # s
    wakeups_per_exchange: float  # the process's sleeps (voluntary context switches)


@contextlib.contextmanager
def simulators(protocol: str, lines: int) -> Iterator[list[str]]:
    procs, ports = [], []
    try:
        for _ in range(lines):
            proc, port = start_simulator(Case(protocol, BAUD, 1, DELAY))
            procs.append(proc)
            ports.append(port)
        yield ports
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(10)


def first_address(protocol: str) -> int:
    return 0 if protocol == "native" else 1


async def gateway(protocol: str, ports: list[str], seconds: float,
                  capture: bool = False) -> Figures:
    """``capture``: with event capture on (its rings filled, nothing written)."""
    config = config_from_dict({"buses": [{
        "name": f"line{i}", "port": port, "baudrate": BAUD, "protocol": protocol,
        "sensors": [{"name": f"s{i}", "series": "AH", "address": first_address(protocol),
                     "poll_hz": 0}]} for i, port in enumerate(ports)],
        **({"capture": {"dir": tempfile.mkdtemp(prefix="bench-captures-")}}
           if capture else {})}, env={})
    gw = Gateway(config)
    stop = asyncio.Event()
    task = asyncio.create_task(gw.run(stop))
    masters = list(gw.masters.values())
    while not all(gw.cache.snapshot(f"s{i}").seq for i in range(len(ports))):
        await asyncio.sleep(0.01)
    t0, c0, w0 = time.monotonic(), time.process_time(), _sleeps()
    n0 = [m.stats.transactions for m in masters]
    b0 = [m.stats.busy_time for m in masters]
    await asyncio.sleep(seconds)
    t1, c1, w1 = time.monotonic(), time.process_time(), _sleeps()
    n1 = [m.stats.transactions for m in masters]
    b1 = [m.stats.busy_time for m in masters]
    stop.set()
    await task
    elapsed = t1 - t0
    done = sum(n1) - sum(n0)
    return Figures([(b - a) / elapsed for a, b in zip(n0, n1, strict=True)],
                   [(b - a) / elapsed for a, b in zip(b0, b1, strict=True)],
                   (c1 - c0) / max(done, 1), (w1 - w0) / max(done, 1))


def bare(protocol: str, ports: list[str], seconds: float) -> Figures:
    """One thread, one select() over every line, a request as soon as the answer
    before it is in (and, for Modbus, the silent interval has passed).  Like the
    gateway, a line whose answer is half in is not watched until the rest could be."""
    adapter = NativeAdapter() if protocol == "native" else ModbusAdapter()
    exchange = adapter.poll(Series.AH, first_address(protocol))
    gap = 0.0 if protocol == "native" else rtu_silence(BAUD)
    ports_open = [serial.Serial(p, BAUD, timeout=0) for p in ports]
    fds = [s.fileno() for s in ports_open]
    got = {fd: 0 for fd in fds}
    done = {fd: 0 for fd in fds}
    # when each line next needs the loop: to send (after the gap), or to read the
    # rest of an answer; 0: waiting for bytes
    send_at = {fd: 0.0 for fd in fds}
    rest_at = {fd: 0.0 for fd in fds}
    try:
        t0, c0, w0 = time.monotonic(), time.process_time(), _sleeps()
        end = t0 + seconds
        for fd in fds:
            os.write(fd, exchange.request)
        while (now := time.monotonic()) < end:
            due = [t for t in (*send_at.values(), *rest_at.values()) if t]
            timeout = max(0.0, min(due) - now) if due else 0.5
            watched = [fd for fd in fds if not send_at[fd] and not rest_at[fd]]
            ready, _, _ = select.select(watched, [], [], min(timeout, end - now))
            now = time.monotonic()
            for fd in fds:
                if fd in ready or (rest_at[fd] and rest_at[fd] <= now):
                    rest_at[fd] = 0.0
                    with contextlib.suppress(BlockingIOError):
                        got[fd] += len(os.read(fd, 4096))
                    if got[fd] >= exchange.answer_bytes:
                        got[fd], done[fd] = 0, done[fd] + 1
                        send_at[fd] = now + gap
                    else:
                        rest_at[fd] = now + (exchange.answer_bytes - got[fd]) * 10 / BAUD
                if send_at[fd] and send_at[fd] <= now:
                    send_at[fd] = 0.0
                    os.write(fd, exchange.request)
        elapsed, cpu, sleeps = time.monotonic() - t0, time.process_time() - c0, _sleeps() - w0
    finally:
        for s in ports_open:
            s.close()
    exchanges = max(sum(done.values()), 1)
    return Figures([done[fd] / elapsed for fd in fds], [], cpu / exchanges, sleeps / exchanges)


def _sleeps() -> int:
    """Times this process's threads have slept and been woken (on a VM each costs
    CPU of its own: docs/benchmarks.md)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_nvcsw


class _AtOnce(SerialLink):
    """A link that keeps each request written (``sent``) and never has bytes of its
    own: the benchmark hands the answers over itself."""

    def __init__(self) -> None:
        super().__init__("(warm)", BAUD)
        self.sent: bytes | None = None

    @property
    def watched(self) -> bool:
        return True

    def write(self, data: bytes, expect: int = 0, look_after: float = 0.0,
              latest: float = math.inf) -> bool:
        self.sent = data
        return True

    def pending(self) -> int:
        return 0

    def set_baudrate(self, baudrate: int) -> None:
        self.baudrate = baudrate


class _Counted:
    """The cache side of a bus master, counting the readings (``BusToCache``)."""

    readings = 0

    def publish(self, name: str, reading: Reading, at: float | None = None) -> object:
        self.readings += 1
        return None

    def set_state(self, name: str, *, online: bool | None = None, busy: bool | None = None,
                  streaming: bool | None = None) -> None:
        pass

    def count_error(self, name: str) -> None:
        pass

    def learn(self, name: str, shown: KnownSettings) -> None:
        pass

    def note_stats(self, bus: BusStats, sensors: Mapping[str, SensorStats]) -> None:
        pass


def warm(protocol: str, exchanges: int = 20000) -> float:
    """``--warm``: process time per exchange (s) of the bus path alone."""
    clock = [1000.0]
    bus_master.BusMaster.now = staticmethod(lambda: clock[0])  # type: ignore[method-assign]
    address = first_address(protocol)
    sensor = make_sensor(WireProtocol[protocol.upper()], Series.AH, address, baud=BAUD)
    config = config_from_dict({"buses": [{
        "name": "warm", "port": "(warm)", "baudrate": BAUD, "protocol": protocol,
        "sensors": [{"name": "s0", "series": "AH", "address": address, "poll_hz": 0}]}]},
        env={})
    link, counted = _AtOnce(), _Counted()
    master = bus_master.BusMaster(config.buses[0], counted, link)
    master.schedule.start(clock[0])
    master.port._opened(None)  # (the port "opened": the first turn)
    answers: dict[bytes, bytes] = {}

    def exchange() -> None:
        while link.sent is None:  # (the RTU gap, or the quiet after the open)
            clock[0] = max(clock[0], master.next_at())
            master.on_timer(clock[0])
        request, link.sent = link.sent, None
        if request not in answers:
            answers[request] = b"".join(o.frame for o in sensor.hear(
                request, clock[0], after_silence=True) if o.solicited)
        clock[0] += 0.004
        master.on_bytes(answers[request], clock[0])

    for _ in range(1000):
        exchange()
    done, c0 = master.stats.transactions, time.process_time()
    for _ in range(exchanges):
        exchange()
    assert counted.readings > exchanges
    return (time.process_time() - c0) / (master.stats.transactions - done)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--lines", type=int, action="append",
                        help="run only this line count (repeatable; default 1, 2, 4, 8)")
    parser.add_argument("--protocol", choices=("native", "modbus"), action="append",
                        help="run only this protocol (repeatable; default: both)")
    parser.add_argument("--capture", action="store_true",
                        help="with event capture on (capture: with its defaults): the "
                        "cost of its rings")
    parser.add_argument("--warm", action="store_true",
                        help="the bus path alone, warm, in one thread: µs per exchange")
    args = parser.parse_args()
    if args.warm:
        for protocol in args.protocol or ("native", "modbus"):
            print(f"{protocol}: the bus path warm, {warm(protocol) * 1e6:.1f} µs per exchange")
        return
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)  # as `imu-gateway run` does
    counts = sorted(set(args.lines or (1, 2, 4, 8)) | {1})  # 1: the reference
    print(f"lines at {BAUD} baud, one AH each, poll_hz 0, answer delay "
          f"{DELAY * 1000:g} ms, {args.seconds} s per run, {os.cpu_count()} CPUs")
    print(f"{'protocol':8} {'lines':>5} {'tx/s/line':>13} {'utilisation':>13} "
          f"{'lowest/single':>13} {'cpu ms/exch':>11} {'bare tx/s/line':>14} "
          f"{'bare cpu ms/exch':>16} {'gw/bare tx':>10}")
    for protocol in args.protocol or ("native", "modbus"):
        single = 0.0
        for lines in counts:
            with simulators(protocol, lines) as ports:
                ref = bare(protocol, ports, args.seconds)
                got = asyncio.run(gateway(protocol, ports, args.seconds, args.capture))
            if lines == 1:
                single = got.utilisation[0]
            low = min(got.utilisation)
            print(f"{protocol:8} {lines:5} {min(got.per_line_tps):6.1f}-"
                  f"{max(got.per_line_tps):<6.1f} {low:6.3f}-{max(got.utilisation):<6.3f} "
                  f"{low / single:13.3f} {got.cpu_per_exchange * 1000:11.3f} "
                  f"{statistics.mean(ref.per_line_tps):14.1f} "
                  f"{ref.cpu_per_exchange * 1000:16.3f} "
                  f"{sum(got.per_line_tps) / sum(ref.per_line_tps):10.3f}", flush=True)
            if lines == 1:
                target = CPU_TARGET[protocol]
                print(f"{'':8} {'':5} cpu per exchange against its target "
                      f"({target * 1000:g} ms): gateway {got.cpu_per_exchange / target:.2f}, "
                      f"bare loop {ref.cpu_per_exchange / target:.2f} "
                      f"({'met' if got.cpu_per_exchange <= target else 'NOT met'}); "
                      f"wake-ups per exchange: gateway {got.wakeups_per_exchange:.2f}, "
                      f"bare loop {ref.wakeups_per_exchange:.2f}", flush=True)


if __name__ == "__main__":
    main()
