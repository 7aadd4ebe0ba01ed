"""Bus master throughput against the wire's limit.

For each protocol, baud rate and sensor count, the simulator runs in its own process
(like real sensors, it shares no interpreter with the gateway) and one bus master
polls every sensor with ``poll_hz: 0``.  Printed per run:

* achieved transactions/s;
* the wire ceiling for those frames at that baud (bytes × 10 / baud,
  plus the RTU silent gaps), and the ceiling once the simulator's answer delay is
  added, which is the most any master could do against these sensors;
* ``achieved/ceiling``: the share of that most the gateway gets;
* utilisation: the time the line was in an exchange (request, answer delay, answer,
  gaps) ÷ elapsed time;
* a reference measured in the same run: a bare blocking pyserial loop polling the
  same simulator (the best it allows), and gateway/bare.

The slow-sensor cases (``--no-slow`` leaves them out) play two sensors at 115200
that answer 35 ms late, then 5-40 ms late (uniformly jittered), against the default
config: the timeout is learned, not set.  Their ceiling counts the mean delay; their
bare loop is told the answer length, so it waits exactly as long as needed.

The dead-sensor case (``--no-absent`` leaves it out) configures 3 live sensors and a
4th the simulator does not play (native, 115200): the gateway probes it; its figures
count the live sensors' exchanges only, and the bare loop polls only those.

Run: ``.venv/bin/python bench/bus.py [--seconds 5] [--delay-ms 2]``; ``--protocol``,
``--baud`` and ``--sensors`` (each repeatable) run only some of the cases.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import time
from dataclasses import dataclass

import serial

from imu_gateway.app import GIL_SWITCH_INTERVAL, Gateway
from imu_gateway.config import config_from_dict
from imu_gateway.model import Series
from imu_gateway.protocol.exchanges import ModbusAdapter, NativeAdapter, char_time, rtu_silence


@dataclass(frozen=True)
class Case:
    protocol: str
    baud: int
    sensors: int
    delay: float  # the sensors' answer delay, s
    jitter: float = 0.0  # plus a uniform random 0..jitter, s
    absent: int = 0  # sensors configured (after the live ones) that nobody plays

    def per_exchange(self, delay: float) -> float:
        """Seconds one poll takes at best: the wire, the gaps, the sensor's delay."""
        if self.protocol == "native":
            exchange = NativeAdapter().poll(Series.AH, 0)
            gaps = 0.0
        else:
            exchange = ModbusAdapter().poll(Series.AH, 1)
            # a silent interval before the request and before the answer
            gaps = 2 * rtu_silence(self.baud)
        wire = (len(exchange.request) + exchange.answer_bytes) * char_time(self.baud)
        return wire + gaps + delay


def bare_loop(case: Case, port: str, seconds: float) -> float:
    """The reference: a plain blocking pyserial loop polling the same simulator in
    turn, reading each answer's exact length.  No schedule, no cache, no threads: the
    best this simulator allows (a real sensor would not have its timing overshoot)."""
    adapter = NativeAdapter() if case.protocol == "native" else ModbusAdapter()
    first = 0 if case.protocol == "native" else 1
    exchanges = [adapter.poll(Series.AH, first + i) for i in range(case.sensors)]
    gap = 0.0 if case.protocol == "native" else rtu_silence(case.baud)
    done = 0
    with serial.Serial(port, case.baud, timeout=1) as ser:
        deadline = time.perf_counter() + seconds
        started = time.perf_counter()
        while time.perf_counter() < deadline:
            exchange = exchanges[done % len(exchanges)]
            time.sleep(gap)
            ser.write(exchange.request)
            if len(ser.read(exchange.answer_bytes)) != exchange.answer_bytes:
                raise SystemExit("the simulator did not answer the reference loop")
            done += 1
        return done / (time.perf_counter() - started)


def start_simulator(case: Case) -> tuple[subprocess.Popen[str], str]:
    first = 0 if case.protocol == "native" else 1
    args = [sys.executable, "-m", "imu_gateway", "simulate", "--answer-delay-ms",
            str(case.delay * 1000), "--jitter-ms", str(case.jitter * 1000)]
    for i in range(case.sensors):
        args += ["--sensor", f"{case.protocol}:AH:{first + i}:{case.baud}"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline().split()
    if not line or line[0] != "PTY":
        proc.kill()
        raise SystemExit("the simulator did not start")
    return proc, line[1]


async def measure(case: Case, port: str, seconds: float) -> dict[str, float]:
    first = 0 if case.protocol == "native" else 1
    config = config_from_dict({"buses": [{
        "name": "bench", "port": port, "baudrate": case.baud, "protocol": case.protocol,
        "sensors": [{"name": f"s{i}", "series": "AH", "address": first + i, "poll_hz": 0}
                    for i in range(case.sensors + case.absent)]}]}, env={})
    gateway = Gateway(config)
    stop = asyncio.Event()
    task = asyncio.create_task(gateway.run(stop))
    master = next(iter(gateway.masters.values()))
    # Let every sensor answer once before the clock starts.
    while not all(gateway.cache.snapshot(f"s{i}").seq for i in range(case.sensors)):
        await asyncio.sleep(0.01)
    loop = asyncio.get_running_loop()
    live = [master.schedule.sensors[f"s{i}"].stats for i in range(case.sensors)]
    t0, n0, busy0 = loop.time(), sum(s.transactions for s in live), master.stats.busy_time
    await asyncio.sleep(seconds)
    t1, n1, busy1 = loop.time(), sum(s.transactions for s in live), master.stats.busy_time
    errors = sum(master.stats.errors.values())
    late, stops = master.stats.late_answers, master.stats.stream_stops
    stop.set()
    await task
    return {"tps": (n1 - n0) / (t1 - t0), "utilisation": (busy1 - busy0) / (t1 - t0),
            "errors": errors, "late": late, "stops": stops}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--delay-ms", type=float, default=2.0,
                        help="the simulated sensors' answer delay")
    parser.add_argument("--protocol", choices=("native", "modbus"), action="append",
                        help="run only this protocol (repeatable; default: both)")
    parser.add_argument("--baud", type=int, choices=(9600, 115200), action="append",
                        help="run only this baud rate (repeatable; default: both)")
    parser.add_argument("--sensors", type=int, choices=(1, 4), action="append",
                        help="run only this sensor count (repeatable; default: both)")
    parser.add_argument("--slow", action=argparse.BooleanOptionalAction, default=True,
                        help="also the slow-sensor cases: two sensors at 115200 answering "
                        "35 ms late, then 5-40 ms (jittered), with the default config")
    parser.add_argument("--absent", action=argparse.BooleanOptionalAction, default=True,
                        help="also the dead-sensor case: 3 live sensors and 1 configured "
                        "but absent, native, 115200")
    args = parser.parse_args()
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)  # as `imu-gateway run` does
    protocols = args.protocol or ("native", "modbus")
    cases = [Case(p, b, n, args.delay_ms / 1000) for p in protocols
             for b in args.baud or (9600, 115200) for n in args.sensors or (1, 4)]
    if args.slow:
        cases += [Case(p, 115200, 2, d, j) for p in protocols
                  for d, j in ((0.035, 0.0), (0.005, 0.035))]
    if args.absent:
        cases.append(Case("native", 115200, 3, args.delay_ms / 1000, absent=1))
    print(f"bus master, poll_hz 0, AH sensors, {args.seconds} s per run, "
          f"{os.cpu_count()} CPUs")
    print(f"{'protocol':8} {'baud':>6} {'sensors':>9} {'delay ms':>8} {'tx/s':>8} "
          f"{'wire max':>9} {'+delay max':>10} {'achieved/max':>12} {'utilisation':>11} "
          f"{'errors':>6} {'late':>5} {'stops':>5} {'bare loop':>9} {'gateway/bare':>12}")
    for case in cases:
        run_case(case, args.seconds)


def run_case(case: Case, seconds: float) -> None:
    proc, port = start_simulator(case)
    try:
        bare = bare_loop(case, port, seconds)
        result = asyncio.run(measure(case, port, seconds))
    finally:
        proc.terminate()
        proc.wait(10)
    wire_max = 1 / case.per_exchange(0.0)
    real_max = 1 / case.per_exchange(case.delay + case.jitter / 2)  # the mean delay
    delay = f"{case.delay * 1000:g}" + (f"+{case.jitter * 1000:g}" if case.jitter else "")
    sensors = f"{case.sensors}" + (f"+{case.absent}x" if case.absent else "")
    print(f"{case.protocol:8} {case.baud:6} {sensors:>9} {delay:>8} {result['tps']:8.1f} "
          f"{wire_max:9.1f} {real_max:10.1f} {result['tps'] / real_max:12.3f} "
          f"{result['utilisation']:11.3f} {result['errors']:6.0f} {result['late']:5.0f} "
          f"{result['stops']:5.0f} {bare:9.1f} {result['tps'] / bare:12.3f}", flush=True)


if __name__ == "__main__":
    main()
