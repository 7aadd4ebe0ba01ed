"""``imu-gateway demo`` as a user runs it (issue 7): a subprocess, every interface
answering with readings of at least two sensors, through the very command lines it
prints (curl, mbpoll, mosquitto_sub against a real mosquitto), then Ctrl-C (SIGINT)
and exit 0.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx
from support.broker import Mosquitto, recording
from support.harness import free_port


def _banner(process: subprocess.Popen[str], timeout: float = 60.0) -> list[str]:
    assert process.stdout is not None
    lines: list[str] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = process.stdout.readline()
        if not line:
            raise AssertionError(f"the demo ended early: {''.join(lines)}")
        lines.append(line.rstrip("\n"))
        if line.startswith("Stop with Ctrl-C"):
            return lines
    raise AssertionError("no banner")


def _printed(lines: list[str], label: str) -> list[str]:
    """The command printed after ``label``, as argv."""
    line = next(line for line in lines if line.startswith(label))
    command = line[len(label):].split("   (")[0].strip()
    return shlex.split(command)


def _wait(condition: Callable[[], bool], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not met"
        time.sleep(0.1)


def test_demo_serves_every_interface_and_stops_on_ctrl_c(tmp_path: Path) -> None:
    http_port, modbus_port, opcua_port = free_port(), free_port(), free_port()
    with Mosquitto(tmp_path) as broker:
        demo = subprocess.Popen(
            [sys.executable, "-m", "imu_gateway", "demo", "--http-port", str(http_port),
             "--modbus-port", str(modbus_port), "--opcua-port", str(opcua_port),
             "--mqtt", broker.url],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            lines = _banner(demo)
            base = f"http://localhost:{http_port}"
            assert f"Dashboard   {base}/" in lines

            # REST: every sensor's reading, and the printed curl line.
            def all_read() -> bool:
                sensors = httpx.get(f"{base}/api/v1/sensors").json()
                return all(s["seq"] >= 1 and s["status"] == "ok" for s in sensors)
            _wait(all_read)
            sensors = httpx.get(f"{base}/api/v1/sensors").json()
            assert len(sensors) >= 2
            assert {s["protocol"] for s in sensors} == {"native", "modbus"}
            assert {s["series"] for s in sensors} >= {"AH", "VG"}
            for sensor in sensors:
                got = httpx.get(f"{base}/api/v1/sensors/{sensor['name']}/reading").json()
                assert got["sensor"] == sensor["name"] and got["status"] == "ok"
            curl = subprocess.run(_printed(lines, "REST"), capture_output=True, text=True,
                                  timeout=20)
            assert "angles" in json.loads(curl.stdout), curl.stdout
            assert httpx.get(f"{base}/").status_code == 200  # the dashboard

            # A command with the printed token.
            result = subprocess.run(_printed(lines, "Commands"), capture_output=True,
                                    text=True, timeout=20)
            assert json.loads(result.stdout)["ok"] is True, result.stdout

            # Modbus TCP: the printed mbpoll line, for two units of two protocols.
            mbpoll = _printed(lines, "Modbus TCP")
            units = {s["unit_id"]: s for s in sensors}
            for unit in (1, next(u for u, s in units.items() if s["protocol"] == "modbus")):
                argv = [*mbpoll]
                argv[argv.index("-a") + 1] = str(unit)
                out = subprocess.run(argv, capture_output=True, text=True, timeout=20).stdout
                values = [float(v) for v in re.findall(r"^\[\d+\]:\s+(\S+)", out, re.M)]
                assert len(values) == 16, out
                assert any(v != 0 for v in values[:3]), out  # pitch, roll, yaw

            # OPC UA: the printed uaread line reads the first sensor's pitch.
            uaread = subprocess.run(_printed(lines, "OPC UA"), capture_output=True,
                                    text=True, timeout=60)
            assert uaread.returncode == 0, uaread.stderr
            float(uaread.stdout.strip().splitlines()[-1])

            # MQTT: the printed mosquitto_sub line, state of two sensors or more.
            sub = [*_printed(lines, "MQTT"), "-W", "15", "-C", "40"]
            assert shutil.which(sub[0]), "mosquitto_sub is not installed"
            out = subprocess.run(sub, capture_output=True, text=True, timeout=30).stdout
            states = {m.group(1) for m in re.finditer(r"^imu/demo/([a-z0-9_-]+)/state ", out,
                                                      re.M)}
            assert len(states) >= 2, out
            # and a command over MQTT 5 with the printed mosquitto_rr line
            rr = next(shlex.split(line.strip()) for line in lines
                      if line.strip().startswith("mosquitto_rr "))
            answer = subprocess.run([*rr, "-W", "15"], capture_output=True, text=True,
                                    timeout=30)
            assert json.loads(answer.stdout)["ok"] is True, (answer.stdout, answer.stderr)

            # the banner says whose broker it is, and that the demo cleans up after itself
            assert f"the demo publishes to the broker it finds at {broker.url}" in \
                next(line for line in lines if line.startswith("MQTT"))
            before = retained_topics(broker)
            assert "imu/demo/status" in before and any("/state" in t for t in before)

            demo.send_signal(signal.SIGINT)
            code = demo.wait(30)
        finally:
            if demo.poll() is None:
                demo.kill()
            _, stderr = demo.communicate()
        assert code == 0
        # nothing of it is left on the broker: no state saying "ok" after it stopped
        assert retained_topics(broker) == set()
        assert f"cleared its {len(before)} retained messages" in stderr


def retained_topics(broker: Mosquitto) -> set[str]:
    """Every retained topic on the broker: those the broker sends at a subscription to
    '#', before a message published after that subscription (which ends the wait)."""
    marker = "test/marker"
    with recording(broker, "#", qos=1) as recorder:
        recorder.client.publish(marker, b"end", qos=1)
        recorder.wait(lambda: recorder.on(marker))
        return {m.topic for m in recorder.messages if m.retain and m.payload}
