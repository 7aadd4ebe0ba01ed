"""``imu-gateway run`` and ``imu-gateway scan`` as processes, against the simulator."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from harness import run, running, until

from gateway.model import Protocol, Series
from gateway.simulator import Faults, make_sensor, simulated


def gateway_cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "gateway", *args]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_run_logs_state_changes_once_and_stops_cleanly(tmp_path: Path, sig: int) -> None:
    faults = Faults(stalled=True)
    with simulated([make_sensor(Protocol.NATIVE, Series.AH, 0, baud=115200),
                    make_sensor(Protocol.NATIVE, Series.VG, 4, baud=115200, faults=faults)]) \
            as sim:
        config = tmp_path / "gateway.yaml"
        config.write_text(f"""
gateway_id: plant
buses:
  - name: line-a
    port: {sim.path}
    baudrate: 115200
    protocol: native
    sensors:
      - {{name: boom, series: AH, address: 0, poll_hz: 0}}
      - {{name: cab, series: VG, address: 4, poll_hz: 0}}
""")
        with subprocess.Popen(gateway_cli("run", "-c", str(config)), stderr=subprocess.PIPE,
                              text=True) as proc:
            # Wait for the event (the silent sensor called offline), not for a time;
            # a watchdog ends a gateway that never says it.
            watchdog = threading.Timer(60, proc.kill)
            watchdog.start()
            assert proc.stderr is not None
            lines = []
            try:
                for line in proc.stderr:
                    lines.append(line)
                    if "sensor cab: offline" in line:
                        break
                proc.send_signal(sig)
                _, rest = proc.communicate(timeout=20)
            finally:
                watchdog.cancel()
            err = "".join(lines) + rest
        assert proc.returncode == 0, err
        assert sim.bus.stats.overlaps == 0
    assert err.count("sensor boom: online") == 1
    assert err.count("sensor cab: offline") == 1
    assert "Traceback" not in err
    assert err.rstrip().endswith("stopped")


def test_run_with_a_bad_config_exits_2_with_the_problems(tmp_path: Path) -> None:
    config = tmp_path / "bad.yaml"
    config.write_text("buses:\n  - name: a\n    port: /dev/null\n    protocol: canbus\n"
                      "    sensors: []\n")
    done = subprocess.run(gateway_cli("run", "-c", str(config)), capture_output=True,
                          text=True, timeout=30, check=False)
    assert done.returncode == 2
    assert "buses[0].protocol:" in done.stderr and "Traceback" not in done.stderr


def test_scan_finds_sensors_of_both_protocols() -> None:
    sensors = [make_sensor(Protocol.NATIVE, Series.AH, 7, baud=19200),
               make_sensor(Protocol.MODBUS, Series.IMU, 3, baud=19200)]
    with simulated(sensors) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--baud", "9600", "--baud", "19200",
                        "--address", "3", "--address", "7", "--address", "9"),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert len(lines) == 2
    assert "native  19200 baud  address   7  series AH" in lines[0]
    assert lines[1].startswith("modbus  19200 baud  address   3  series IMU")
    assert sim.bus.stats.internal_errors == 0


def test_scan_tells_several_native_sensors_apart() -> None:
    """The address query collides when several answer; scan then asks each address."""
    sensors = [make_sensor(Protocol.NATIVE, Series.IMU, 1, baud=115200),
               make_sensor(Protocol.NATIVE, Series.VG, 2, baud=115200)]
    with simulated(sensors) as sim:
        done = subprocess.run(
            # 256 addresses are asked in turn: fast sensors, a short margin (the default
            # margin is for slow ones: test_scan_finds_slow_sensors_with_its_defaults)
            gateway_cli("scan", "--port", sim.path, "--baud", "115200", "--protocol", "native",
                        "--margin-ms", "20"),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert [line.split()[4] for line in done.stdout.splitlines()] == ["1", "2"]
    assert "series VG or MINS" in done.stdout


def test_scan_of_a_missing_port_is_one_clear_error() -> None:
    done = subprocess.run(gateway_cli("scan", "--port", "/dev/does-not-exist"),
                          capture_output=True, text=True, timeout=30, check=False)
    assert done.returncode == 2
    assert "/dev/does-not-exist" in done.stderr and "Traceback" not in done.stderr


def test_scan_of_an_empty_line_finds_nothing(tmp_path: Path) -> None:
    with simulated([]) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--baud", "115200", "--address", "1"),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 1
    assert "0 sensors found" in done.stderr


def test_scan_finds_native_sensors_whose_address_answers_do_not_collide() -> None:
    sensors = [make_sensor(Protocol.NATIVE, Series.AH, 4, baud=115200, answer_delay=0.002),
               make_sensor(Protocol.NATIVE, Series.IMU, 9, baud=115200, answer_delay=0.02)]
    with simulated(sensors) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--baud", "115200", "--protocol", "native"),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert [line.split()[4] for line in done.stdout.splitlines()] == ["4", "9"]


@pytest.mark.parametrize("protocol", ["native", "modbus"])
def test_scan_finds_slow_sensors_with_its_defaults(protocol: str) -> None:
    """Sensors that answer 35 ms late, and 5-40 ms late (jittered), behind defaults."""
    first = 0 if protocol == "native" else 1
    sensors = [make_sensor(Protocol[protocol.upper()], Series.AH, first + 4, baud=115200,
                           answer_delay=0.035),
               make_sensor(Protocol[protocol.upper()], Series.AH, first + 9, baud=115200,
                           answer_delay=0.005, jitter=0.035, seed=3)]
    with simulated(sensors) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--baud", "115200", "--protocol", protocol,
                        *[f"--address={a}" for a in range(first, first + 12)]),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert [line.split()[4] for line in done.stdout.splitlines()] == \
        [str(first + 4), str(first + 9)]


def test_a_second_program_on_the_gateways_port_gets_a_clear_error() -> None:
    """One owner per line: the gateway opens its device exclusively, so a scan (or a
    second gateway) started on the same port is refused at once, and the gateway
    carries on."""
    with simulated([make_sensor(Protocol.NATIVE, Series.AH, 0, baud=115200)]) as sim:
        async def body() -> None:
            async with running({"buses": [{
                    "name": "a", "port": sim.path, "baudrate": 115200, "protocol": "native",
                    "sensors": [{"name": "boom", "series": "AH", "poll_hz": 20}]}]}) as gw:
                await until(lambda: gw.cache.snapshot("boom").seq >= 1)
                done = await asyncio.to_thread(
                    subprocess.run, gateway_cli("scan", "--port", sim.path, "--baud", "115200"),
                    capture_output=True, text=True, timeout=60, check=False)
                assert done.returncode == 2, done.stderr
                assert "exclusively lock" in done.stderr and "Traceback" not in done.stderr
                seq = gw.cache.snapshot("boom").seq
                await until(lambda: gw.cache.snapshot("boom").seq > seq + 5)
                assert sim.bus.stats.overlaps == 0

        run(body)
