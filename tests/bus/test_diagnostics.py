"""What a field engineer is told when a sensor does not answer: the real gateway
process on a simulated line, set up with each of the usual mistakes."""

from __future__ import annotations

import re
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, make_sensor, simulated

FAST = 115200


def log_until(config: dict[str, Any], path: Path, done: Callable[[list[str]], bool],
              *options: str) -> list[str]:
    """Run the gateway on ``config`` (written to ``path``) until ``done(lines)`` holds
    for its log so far; the log's lines."""
    path.write_text(yaml.safe_dump(config))
    with subprocess.Popen([sys.executable, "-m", "imu_gateway", "run", "-c", str(path),
                           *options], stderr=subprocess.PIPE, text=True) as proc:
        watchdog = threading.Timer(60, proc.kill)  # a gateway that never says it
        watchdog.start()
        assert proc.stderr is not None
        lines: list[str] = []
        try:
            for line in proc.stderr:
                lines.append(line)
                if done(lines):
                    break
        finally:
            watchdog.cancel()
            proc.terminate()
            proc.communicate(timeout=20)
    return lines


def first_line_with(tmp_path: Path, port: str, sensor: dict[str, Any], needle: str,
                    protocol: str = "native", baud: int = FAST) -> tuple[str, str]:
    """Run the gateway on ``port`` with one configured sensor until a log line holds
    ``needle``; that line, and the whole log up to it."""
    config = {"gateway_id": "diag", "buses": [{
        "name": "line", "port": port, "baudrate": baud, "protocol": protocol,
        "sensors": [sensor]}]}
    lines = log_until(config, tmp_path / "gateway.yaml", lambda seen: needle in seen[-1])
    found = [line for line in lines if needle in line]
    assert found, "".join(lines)
    return found[0], "".join(lines)


def streaming(protocol: WireProtocol, series: Series, address: int, baud: int) -> SimSensor:
    """A sensor left streaming (its saved auto-output), as many are found on site."""
    return make_sensor(protocol, series, address, baud=baud, stream_interval=0.05)


def test_a_silent_line_says_nothing_came_back(tmp_path: Path) -> None:
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=9600)]) as line:
        text, _ = first_line_with(tmp_path, line.path, {"name": "mast", "series": "AH"},
                                  "sensor mast: offline")
    assert "never answered, native address 0 at 115200 baud" in text
    assert "nothing came back" in text and "baud rate" in text
    assert f"imu-gateway scan --port {line.path}" in text


def test_the_wrong_baud_rate_is_named_when_bytes_arrive(tmp_path: Path) -> None:
    with simulated([streaming(WireProtocol.NATIVE, Series.AH, 0, 9600)]) as line:
        text, _ = first_line_with(tmp_path, line.path, {"name": "mast", "series": "AH"},
                                  "sensor mast: offline")
    assert "never formed a frame at 115200 baud: wrong baud rate?" in text


def test_the_wrong_address_is_named_when_frames_come_from_another(tmp_path: Path) -> None:
    with simulated([streaming(WireProtocol.NATIVE, Series.AH, 5, FAST)]) as line:
        text, _ = first_line_with(tmp_path, line.path,
                                  {"name": "mast", "series": "AH", "address": 3},
                                  "sensor mast: offline")
    assert "native address 3" in text
    assert "frames come from address 5, not 3: wrong address?" in text


def test_the_wrong_protocol_is_named(tmp_path: Path) -> None:
    with simulated([streaming(WireProtocol.MODBUS, Series.AH, 1, FAST)]) as line:
        text, _ = first_line_with(tmp_path, line.path, {"name": "mast", "series": "AH"},
                                  "sensor mast: offline")
    assert "Modbus RTU frames arrive (unit 1): wrong protocol?" in text


@pytest.mark.parametrize(("real", "configured", "shape"),
                         [(Series.AH, "VG", "0x59, LEN 0x38"),
                          (Series.VG, "AH", "0x59, LEN 0x2F")])
def test_the_wrong_series_is_named_at_once_and_nothing_is_written(
        tmp_path: Path, real: Series, configured: str, shape: str) -> None:
    sim = make_sensor(WireProtocol.NATIVE, real, 0, baud=FAST)
    with simulated([sim]) as line:
        text, log = first_line_with(tmp_path, line.path,
                                    {"name": "mast", "series": configured},
                                    "sensor mast: answers like")
    assert f"({shape}); the config says {configured}" in text
    assert text.count("answers like") == 1
    assert "stream" not in log  # not taken for a stream nobody asked for
    assert not sim.writes_heard  # and nothing was written to it


def test_the_frame_trace_shows_each_exchange_and_is_rate_limited(tmp_path: Path) -> None:
    """``--trace BUS``: one line per exchange (bytes out, bytes in, time, outcome);
    a sensor polled flat out makes more than the 50 a second shown."""
    ah = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST)
    silent = make_sensor(WireProtocol.NATIVE, Series.VG, 4, baud=9600)  # never answers
    with simulated([ah, silent]) as line:
        config = {"gateway_id": "diag", "buses": [{
            "name": "line", "port": line.path, "baudrate": FAST, "protocol": "native",
            "sensors": [{"name": "boom", "series": "AH", "poll_hz": 0},
                        {"name": "mast", "series": "VG", "address": 4}]}]}
        lines = log_until(config, tmp_path / "gateway.yaml",
                          lambda seen: "exchanges not shown" in seen[-1]
                          and any("timeout" in x for x in seen), "--trace", "line")
    log = "".join(lines)
    ok = re.compile(r"gateway\.trace: bus line: boom tx 77 04 00 59 5D \| rx 77 38 00 59 "
                    r"(?:[0-9A-F]{2} ){6}… [0-9A-F]{2} [0-9A-F]{2} \(57 B, \d+\.\d ms\) ok$",
                    re.MULTILINE)
    assert ok.search(log), log[-3000:]
    assert re.search(r"bus line: mast tx 77 04 04 59 61 \| rx nothing \(\d+\.\d ms\) "
                     r"timeout \(try 1 of 2\)", log), log[-3000:]
    assert re.search(r"bus line: trace: \d+ exchanges not shown \(more than 50 a second\)",
                     log)


def test_a_bad_trace_bus_is_refused(tmp_path: Path) -> None:
    config = tmp_path / "gateway.yaml"
    config.write_text(yaml.safe_dump({"buses": [{
        "name": "line", "port": "/dev/null", "protocol": "native",
        "sensors": [{"name": "boom", "series": "AH"}]}]}))
    done = subprocess.run([sys.executable, "-m", "imu_gateway", "run", "-c", str(config),
                           "--trace", "lime"], capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 2
    assert "--trace lime: no such bus (the buses: line)" in done.stderr


def test_check_config_warns_of_a_poll_that_fits_no_pause_of_a_stream(tmp_path: Path) -> None:
    def check(baudrate: int) -> str:
        config = tmp_path / "gateway.yaml"
        config.write_text(yaml.safe_dump({"buses": [{
            "name": "boom", "port": str(tmp_path / "ttyUSB9"), "protocol": "native",
            "baudrate": baudrate, "sensors": [
                {"name": "tilt", "series": "AH", "address": 1, "poll_hz": 0},
                {"name": "nav", "series": "MINS", "address": 2, "stream_hz": 100}]}]}))
        done = subprocess.run([sys.executable, "-m", "imu_gateway", "check-config", "-c",
                               str(config)], capture_output=True, text=True, timeout=60,
                              check=False)
        assert done.returncode == 0, done.stderr
        return done.stdout

    # 115200: (5 + 57 B) x 10 / 115200 + 2 ms = 7.4 ms against 10 ms - 48 B x 10 / 115200
    # - 1 ms of wobble - 1 ms of quiet = 3.8 ms
    out = check(115200)
    assert "warning: bus boom: tilt's exchange (7.4 ms, with a fast sensor's answer delay) " \
           "does not fit the pauses of nav's 100 Hz stream (3.8 ms," in out, out
    assert "raise the baud rate, lower stream_hz, or put tilt on another line" in out
    assert "fit the pauses" not in check(460800)  # 3.3 ms against 6.9 ms


def test_check_config_warns_of_an_overloaded_line_and_a_missing_port(tmp_path: Path) -> None:
    config = tmp_path / "gateway.yaml"
    config.write_text(yaml.safe_dump({"buses": [{
        "name": "slow", "port": str(tmp_path / "ttyUSB9"), "protocol": "native",
        "baudrate": 9600, "sensors": [{"name": "a", "series": "AH", "poll_hz": 10},
                                      {"name": "b", "series": "AH", "address": 1,
                                       "poll_hz": 10}]}]}))
    done = subprocess.run([sys.executable, "-m", "imu_gateway", "check-config", "-c",
                           str(config)], capture_output=True, text=True, timeout=60,
                          check=False)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    # 2 x 10/s x (5 + 57 B) x 10 / 9600 = 1.29 s/s of wire, plus 2 ms a turnaround
    assert "bus slow at 9600 baud: a 10/s (poll), b 10/s (poll): wire 1.29 s/s" in out, out
    assert "= 1.33 of the line" in out, out
    assert "warning: bus slow: the configured rates ask 1.33 times what 9600 baud " \
           "carries" in out, out
    assert f"warning: bus slow: the port {tmp_path / 'ttyUSB9'} does not exist now" in out
