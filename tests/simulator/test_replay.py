"""Replay (docs/simulator.md, "Replay"; issue 31 §4): a capture taken with
``POST /api/v1/captures`` on a noisy line with a slow sensor, played back into a fresh
gateway, gives that gateway the first one's readings, in order, and its errors.

The first gateway's capture window covers its whole run (``pre_s`` longer than it
ran): a replay answers only the requests the capture holds, and the requests a
gateway makes at its start (a sensor found online has its settings read) are in it.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import select
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.harness import interrupt, running, until

from imu_gateway.cache import EventKind, Snapshot
from imu_gateway.derived import values_of
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, make_sensor, simulated
from imu_gateway.simulator.motion import Motion
from imu_gateway.simulator.replay import load, replaying

FAST = 115200
TOKEN = "t0ken-for-replay"


def config(port: str, protocol: str, series: str, folder: Path | None) -> dict[str, Any]:
    out: dict[str, Any] = {
        "gateway_id": "replay", "buses": [{
            "name": "line", "port": port, "baudrate": FAST, "protocol": protocol,
            "timeout_ms": 250, "retries": 1,
            "sensors": [{"name": "boom", "series": series, "poll_hz": 20}]}]}
    if folder is not None:
        out["http"] = {"listen": "127.0.0.1:0", "token": TOKEN, "allow_commands": True}
        out["capture"] = {"dir": str(folder), "pre_s": 60, "post_s": 0.2}
    return out


Row = tuple[tuple[float | None, ...], int]  # a reading's values, and the errors by then


def captured_rows(archive: zipfile.ZipFile) -> tuple[list[str], list[Row]]:
    rows = list(csv.DictReader(io.StringIO(archive.read("boom.csv").decode())))
    # (the vibration is worked out over the last second by receive time: a replay
    # gives the same samples at other times, and beside CPU burners a window with one
    # sample fewer, NaN against 0.0, is the machine's doing, not the replay's)
    fields = [f for f in rows[0] if f not in ("kind", "wire_time", "wire_s", "receive_time",
                                             "receive_s", "seq", "status", "errors",
                                             "vibration")]
    return fields, [(tuple(float(r[f]) if r[f] else None for f in fields), int(r["errors"]))
                    for r in rows if r["kind"] == "reading"]


@pytest.mark.anyio
@pytest.mark.parametrize("protocol, series", [("native", "AH"), ("modbus", "VG")])
async def test_a_replayed_capture_gives_a_fresh_gateway_the_same_readings_and_errors(
        protocol: str, series: str, tmp_path: Path) -> None:
    # a slow sensor (30 ms to answer) on a line with noise, and some answers garbled:
    # errors to replay.  The timeout leaves the second gateway room for a busy
    # machine: an answer it gives up on before it comes is a reading the first had and
    # it cannot (CI beside CPU burners, with 60 ms: 30 s without all of them)
    sim = make_sensor(WireProtocol(WireProtocol[protocol.upper()]), Series[series],
                      baud=FAST, source=Motion.from_seed(7), answer_delay=0.03,
                      faults=Faults(corrupt_rate=0.08), seed=7)
    folder = tmp_path / "captures"
    with simulated([sim], noise_rate=4.0, seed=7) as line:
        async with running(config(line.path, protocol, series, folder)) as first:
            assert first.http is not None
            await until(lambda: first.cache.snapshot("boom").seq >= 40
                        and first.cache.snapshot("boom").errors >= 2, timeout=30)
            async with httpx.AsyncClient(
                    base_url=f"http://127.0.0.1:{first.http.port}") as http:
                posted = await http.post("/api/v1/captures",
                                         headers={"Authorization": f"Bearer {TOKEN}"})
                assert posted.status_code == 202
                capture_id = posted.json()["id"]
                await until(lambda: (folder / f"{capture_id}.zip").exists())
    path = folder / f"{capture_id}.zip"
    fields, recorded = captured_rows(zipfile.ZipFile(path))
    assert recorded[-1][1] >= 2, "the run to replay has errors"

    replayed: list[Row] = []

    def note(kind: EventKind, snap: Snapshot) -> None:
        if kind is EventKind.READING:
            values = values_of(snap)
            # (a value the sensor cannot give, NaN, is an empty cell in the CSV)
            replayed.append((tuple(None if (v := values.get(f)) is None or math.isnan(v)
                                   else v for f in fields), snap.errors))

    with replaying(path) as replay:
        async with running(config(replay.paths["line"], protocol, series, None)) as second:
            second.cache.subscribe(note)
            await until(lambda: len(replayed) >= len(recorded), timeout=30)
        summary = replay.replay.summary()["line"]
    assert [values for values, _ in replayed[:len(recorded)]] == \
        [values for values, _ in recorded]
    assert [errors for _, errors in replayed[:len(recorded)]] == \
        [errors for _, errors in recorded], summary
    assert summary["answered"] > len(recorded)


def ask(path: Path, request: bytes, size: int) -> bytes:
    """Write ``request`` to the pty, and read up to ``size`` bytes for a second."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        os.write(fd, request)
        got = b""
        deadline = time.monotonic() + 1.0
        while len(got) < size and time.monotonic() < deadline:
            if select.select([fd], [], [], 0.05)[0]:
                got += os.read(fd, 64)
        return got
    finally:
        os.close(fd)


def test_the_command_line_replays_a_capture(tmp_path: Path) -> None:
    """``imu-gateway simulate --replay capture.zip --link PATH``: a pty per line, at
    ``PATH``; a file that is not a capture is one clear error."""
    capture = tmp_path / "capture.zip"
    with zipfile.ZipFile(capture, "w") as archive:
        archive.writestr("meta.json", json.dumps({"buses": [{"name": "line"}]}))
        archive.writestr("frames.jsonl", json.dumps(
            {"bus": "line", "t": 1.0, "dir": "tx", "hex": "7704005963"}) + "\n" + json.dumps(
            {"bus": "line", "t": 1.01, "dir": "rx", "hex": "770500590065"}) + "\n")
    assert load(capture)[0].answers == {
        bytes.fromhex("7704005963"): load(capture)[0].answers[bytes.fromhex("7704005963")]}
    link = tmp_path / "line"
    with subprocess.Popen(
            [sys.executable, "-m", "imu_gateway", "simulate", "--replay", str(capture),
             "--link", str(link)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True) as process:
        try:
            assert process.stdout is not None
            first = process.stdout.readline().split()
            assert first[0] == "PTY" and first[2] == "line" and link.resolve() == Path(first[1])
            assert ask(link, bytes.fromhex("7704005963"), 6) == bytes.fromhex("770500590065")
            assert ask(link, bytes.fromhex("7704005963"), 6) == b""  # no more of it: silence
        finally:
            assert interrupt(process) == 0
            assert process.stderr is not None
            assert '"answered": 1' in process.stderr.read()
        assert not link.exists()
    bad = tmp_path / "not.zip"
    bad.write_text("hello")
    result = subprocess.run([sys.executable, "-m", "imu_gateway", "simulate", "--replay",
                             str(bad)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "is not a capture" in result.stderr
    assert result.stderr.count("\n") == 1, result.stderr
