"""What a field engineer is told when a sensor does not answer: the real gateway
process on a simulated line, set up with each of the usual mistakes."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import yaml

from gateway.model import Protocol, Series
from gateway.simulator import SimSensor, make_sensor, simulated

FAST = 115200


def first_line_with(tmp_path: Path, port: str, sensor: dict[str, Any], needle: str,
                    protocol: str = "native", baud: int = FAST) -> tuple[str, str]:
    """Run the gateway on ``port`` with one configured sensor until a log line holds
    ``needle``; that line, and the whole log up to it."""
    config = tmp_path / "gateway.yaml"
    config.write_text(yaml.safe_dump({"gateway_id": "diag", "buses": [{
        "name": "line", "port": port, "baudrate": baud, "protocol": protocol,
        "sensors": [sensor]}]}))
    with subprocess.Popen([sys.executable, "-m", "gateway", "run", "-c", str(config)],
                          stderr=subprocess.PIPE, text=True) as proc:
        watchdog = threading.Timer(60, proc.kill)  # a gateway that never says it
        watchdog.start()
        assert proc.stderr is not None
        lines: list[str] = []
        try:
            for line in proc.stderr:
                lines.append(line)
                if needle in line:
                    break
        finally:
            watchdog.cancel()
            proc.terminate()
            proc.communicate(timeout=20)
    found = [line for line in lines if needle in line]
    assert found, "".join(lines)
    return found[0], "".join(lines)


def streaming(protocol: Protocol, series: Series, address: int, baud: int) -> SimSensor:
    """A sensor left streaming (its saved auto-output), as many are found on site."""
    return make_sensor(protocol, series, address, baud=baud, stream_interval=0.05)


def test_a_silent_line_says_nothing_came_back(tmp_path: Path) -> None:
    with simulated([make_sensor(Protocol.NATIVE, Series.AH, 0, baud=9600)]) as line:
        text, _ = first_line_with(tmp_path, line.path, {"name": "mast", "series": "AH"},
                                  "sensor mast: offline")
    assert "never answered, native address 0 at 115200 baud" in text
    assert "nothing came back" in text and "baud rate" in text
    assert f"imu-gateway scan --port {line.path}" in text


def test_the_wrong_baud_rate_is_named_when_bytes_arrive(tmp_path: Path) -> None:
    with simulated([streaming(Protocol.NATIVE, Series.AH, 0, 9600)]) as line:
        text, _ = first_line_with(tmp_path, line.path, {"name": "mast", "series": "AH"},
                                  "sensor mast: offline")
    assert "never formed a frame at 115200 baud: wrong baud rate?" in text


def test_the_wrong_address_is_named_when_frames_come_from_another(tmp_path: Path) -> None:
    with simulated([streaming(Protocol.NATIVE, Series.AH, 5, FAST)]) as line:
        text, _ = first_line_with(tmp_path, line.path,
                                  {"name": "mast", "series": "AH", "address": 3},
                                  "sensor mast: offline")
    assert "native address 3" in text
    assert "frames come from address 5, not 3: wrong address?" in text


def test_the_wrong_protocol_is_named(tmp_path: Path) -> None:
    with simulated([streaming(Protocol.MODBUS, Series.AH, 1, FAST)]) as line:
        text, _ = first_line_with(tmp_path, line.path, {"name": "mast", "series": "AH"},
                                  "sensor mast: offline")
    assert "Modbus RTU frames arrive (unit 1): wrong protocol?" in text


@pytest.mark.parametrize(("real", "configured", "shape"),
                         [(Series.AH, "VG", "0x59, LEN 0x38"),
                          (Series.VG, "AH", "0x59, LEN 0x2F")])
def test_the_wrong_series_is_named_at_once_and_nothing_is_written(
        tmp_path: Path, real: Series, configured: str, shape: str) -> None:
    sim = make_sensor(Protocol.NATIVE, real, 0, baud=FAST)
    with simulated([sim]) as line:
        text, log = first_line_with(tmp_path, line.path,
                                    {"name": "mast", "series": configured},
                                    "sensor mast: answers like")
    assert f"({shape}); the config says {configured}" in text
    assert text.count("answers like") == 1
    assert "stream" not in log  # not taken for a stream nobody asked for
    assert not sim.writes_heard  # and nothing was written to it
