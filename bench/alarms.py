"""The alarms' CPU per sample (issue 31): what evaluating 10 alarms per sensor adds to
a sample's path through the cache, against the same gateway without alarms.

A ``Gateway`` on 4 AH sensors (not started: no bus, no front end; the cache with its
listeners, the history and the alarms, as on the main loop) takes readings put into
its cache in a loop, as the bus hand-over does.  Cases, each for ``--samples``
samples, in turn for ``--rounds`` rounds:

* ``none``: no alarm configured (each sensor's built-in communication alarm is not
  evaluated per sample);
* ``quiet``: 10 alarms per sensor, on 10 different fields, none ever crossed (the
  usual case: a sample moves no alarm);
* ``moving``: the same, one of them (pitch) crossed and back on every sample, so each
  sample makes a transition, an ``ALARM`` event and a journal line written by the
  journal's thread to a file (the worst case, far beyond any real sensor).

Printed: process time per sample (µs) of each case and the difference to ``none``
(the alarms' cost).  Run: ``.venv/bin/python bench/alarms.py [--samples 20000]
[--rounds 3]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from imu_gateway.app import Gateway
from imu_gateway.config import config_from_dict
from imu_gateway.model import Reading
from imu_gateway.simulator.motion import Motion

SENSORS = 4
FIELDS = ("pitch", "roll", "yaw", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y",
          "gyro_z", "mag_x")


def config(case: str, journal: str | None) -> dict[str, Any]:
    """Band alarms (-500..500: no value of the motion gets there); in ``moving`` the
    pitch's is -500..0, which the pitch crosses at every sample."""
    rows = [{"name": f"a_{f}", "field": f, "below": -500.0, "hysteresis": 1.0,
             "above": 0.0 if case == "moving" and f == "pitch" else 500.0}
            for f in FIELDS] if case != "none" else []
    out: dict[str, Any] = {
        "gateway_id": "bench",
        "buses": [{"name": "a", "port": "/dev/null-bench", "protocol": "native",
                   "sensors": [{"name": f"s{i}", "series": "AH", "address": i,
                                "alarms": rows} for i in range(SENSORS)]}]}
    if journal is not None:
        out["alarm_journal"] = journal
    return out


def readings(n: int) -> list[Reading]:
    """Moving values, the pitch -10 and 10 in turn for each sensor."""
    motion = Motion.from_seed(1)
    out = []
    for i in range(n):
        reading = motion.sample(i * 0.01)
        assert reading.angles is not None
        out.append(replace(reading, angles=replace(
            reading.angles, pitch=(10.0 if i // SENSORS % 2 else -10.0))))
    return out


def run(case: str, samples: int, folder: str) -> float:
    """Process time per sample, µs."""
    journal = str(Path(folder) / f"{case}.jsonl") if case == "moving" else None
    gateway = Gateway(config_from_dict(config(case, journal), env={}))
    feed = readings(samples)
    cache = gateway.cache
    names = [f"s{i}" for i in range(SENSORS)]
    start = time.process_time()
    for i, reading in enumerate(feed):
        cache.publish(names[i % SENSORS], reading)
    if gateway.journal_file is not None:  # (its thread's CPU counts: it is the process's)
        gateway.journal_file.close(timeout=60)
        assert gateway.journal_file.errors == 0
    spent = time.process_time() - start
    moved = sum(gateway.alarm_counts().transitions.values())
    assert moved >= samples - SENSORS if case == "moving" else moved == 0, (case, moved)
    return spent / samples * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=20000)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    cases = ("none", "quiet", "moving")
    got: dict[str, list[float]] = {c: [] for c in cases}
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(args.rounds):
            for case in cases:
                got[case].append(run(case, args.samples, folder))
    for case in cases:
        extra = [a - b for a, b in zip(got[case], got["none"], strict=True)]
        print(f"{case:7s} {min(got[case]):7.1f}-{max(got[case]):7.1f} µs/sample"
              + ("" if case == "none" else
                 f"   alarms: {min(extra):+6.1f} to {max(extra):+6.1f} µs/sample"))


if __name__ == "__main__":
    main()
