"""``imu-gateway run`` and ``imu-gateway scan`` as processes, against the simulator."""

from __future__ import annotations

import asyncio
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import serial
from support.harness import run, running, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.protocol import modbus_rtu as rtu
from imu_gateway.simulator import Faults, make_sensor, simulated


def gateway_cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "imu_gateway", *args]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_run_logs_state_changes_once_and_stops_cleanly(tmp_path: Path, sig: int) -> None:
    faults = Faults(stalled=True)
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200),
                    make_sensor(WireProtocol.NATIVE, Series.VG, 4, baud=115200, faults=faults)]) \
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
        assert sim.bus.stats.masters_overlaps == 0, "\n\n".join(  # (each whole, timed)
            "\n".join(incident) for incident in sim.bus.stats.incidents)
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
    sensors = [make_sensor(WireProtocol.NATIVE, Series.AH, 7, baud=19200),
               make_sensor(WireProtocol.MODBUS, Series.IMU, 3, baud=19200)]
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
    # Both protocols found, at one rate: the rate alone would have been enough.
    assert f"next time: imu-gateway scan --port {sim.path} --baud 19200\n" in done.stderr


def test_scan_tells_several_native_sensors_apart() -> None:
    """The address query collides when several answer; scan then asks each address."""
    sensors = [make_sensor(WireProtocol.NATIVE, Series.IMU, 1, baud=115200),
               make_sensor(WireProtocol.NATIVE, Series.VG, 2, baud=115200)]
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
    sensors = [make_sensor(WireProtocol.NATIVE, Series.AH, 4, baud=115200, answer_delay=0.002),
               make_sensor(WireProtocol.NATIVE, Series.IMU, 9, baud=115200, answer_delay=0.02)]
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
    sensors = [make_sensor(WireProtocol[protocol.upper()], Series.AH, first + 4, baud=115200,
                           answer_delay=0.035),
               make_sensor(WireProtocol[protocol.upper()], Series.AH, first + 9, baud=115200,
                           answer_delay=0.005, jitter=0.035, seed=3)]
    with simulated(sensors) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--baud", "115200", "--protocol", protocol,
                        *[f"--address={a}" for a in range(first, first + 12)]),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert [line.split()[4] for line in done.stdout.splitlines()] == \
        [str(first + 4), str(first + 9)]


@pytest.mark.anyio
async def test_a_second_program_on_the_gateways_port_gets_a_clear_error() -> None:
    """One owner per line: the gateway opens its device exclusively, so a scan (or a
    second gateway) started on the same port is refused at once, and the gateway
    carries on."""
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200)]) as sim:
        async with running({"buses": [{
                "name": "a", "port": sim.path, "baudrate": 115200, "protocol": "native",
                "sensors": [{"name": "boom", "series": "AH", "poll_hz": 20}]}]}) as gw:
            await until(lambda: gw.cache.snapshot("boom").seq >= 1)
            done = await asyncio.to_thread(
                subprocess.run, gateway_cli("scan", "--port", sim.path, "--baud", "115200"),
                capture_output=True, text=True, timeout=60, check=False)
            assert done.returncode == 2, done.stderr
            assert f"{sim.path} is in use by another process: stop the gateway first" \
                in done.stderr and "Traceback" not in done.stderr
            seq = gw.cache.snapshot("boom").seq
            await until(lambda: gw.cache.snapshot("boom").seq > seq + 5)
            assert sim.bus.stats.masters_overlaps == 0



def test_scan_reports_progress_with_an_estimate_of_the_time_left() -> None:
    """A line at each step's start, and within a step one about every second: 16 units
    at the default margin (100 ms each when silent) last over a second whatever the
    machine's speed, so at least one line names an address."""
    with simulated([make_sensor(WireProtocol.MODBUS, Series.AH, 16, baud=115200)]) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--protocol", "modbus", "--baud", "9600",
                        "--baud", "115200", *[f"--address={a}" for a in range(1, 17)]),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("modbus 115200 baud  address  16")
    progress = [line for line in done.stderr.splitlines() if line.startswith("scanning")]
    assert re.fullmatch(r"scanning modbus 9600 baud, 16 addresses \(about \d s left\)",
                        progress[0]), progress
    assert any(re.fullmatch(r"scanning modbus 115200 baud, 16 addresses "
                            r"\(about \d s left\)", line) for line in progress), progress
    assert any(re.fullmatch(r"scanning modbus \d+ baud, address \d+ \(\d+ of 16; "
                            r"about \d s left\)", line) for line in progress), progress
    seconds = [int(m[1]) for line in progress if (m := re.search(r"about (\d+) s", line))]
    assert seconds == sorted(seconds, reverse=True)


def test_scan_stop_after_ends_the_scan_at_the_first_sensor_found() -> None:
    sensors = [make_sensor(WireProtocol.NATIVE, Series.AH, 7, baud=9600),
               make_sensor(WireProtocol.NATIVE, Series.VG, 8, baud=115200)]
    with simulated(sensors) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--protocol", "native", "--baud", "9600",
                        "--baud", "115200", "--stop-after", "1"),
            capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["native   9600 baud  address   7  series AH"]
    # Every step's start is reported (not throttled): 115200 was never begun.
    assert "scanning native 9600 baud" in done.stderr
    assert "115200 baud" not in done.stderr
    assert "1 sensor found (stopped: --stop-after 1)" in done.stderr
    assert done.stderr.rstrip().endswith(
        f"next time: imu-gateway scan --port {sim.path} --protocol native --baud 9600")


def test_scan_of_a_port_held_open_exclusively_says_it_is_in_use() -> None:
    with simulated([]) as sim, serial.Serial(sim.path, exclusive=True):  # as the gateway does
        done = subprocess.run(gateway_cli("scan", "--port", sim.path, "--baud", "115200"),
                              capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2
    assert done.stderr == (f"imu-gateway scan: error: {sim.path} is in use by another "
                           f"process: stop the gateway first (it holds {sim.path}); "
                           f"`fuser -v {sim.path}` shows who has it\n")


@pytest.mark.parametrize("all_addresses", [False, True])
def test_scan_asks_reserved_modbus_units_only_with_all_addresses(all_addresses: bool) -> None:
    """The requests on the line (the simulator cannot play a sensor at 248-255: its
    framing drops such units, like the gateway's; tests/tools/test_scan.py hears one)."""
    addresses = [f"--address={a}" for a in (0, 247, *range(248, 256))]
    asked = 9 if all_addresses else 1  # 247 (and 248-255), never 0
    request_bytes = len(rtu.read_request(1, 0x04, 1))
    with simulated([]) as sim:
        done = subprocess.run(
            gateway_cli("scan", "--port", sim.path, "--protocol", "modbus", "--baud", "115200",
                        "--margin-ms", "10", *addresses,
                        *(["--all-addresses"] if all_addresses else [])),
            capture_output=True, text=True, timeout=60, check=False)
        # The simulator thread may take the last request in after the scan has ended.
        run(lambda: until(lambda: sim.bus.stats.requests_bytes >= asked * request_bytes))
        assert sim.bus.stats.requests_bytes == asked * request_bytes
    assert done.returncode == 1, done.stderr
    skipped = "0" if all_addresses else "0, 248, 249, 250, 251, 252, 253, 254, 255"
    assert f"note: Modbus does not ask {skipped} (0 is broadcast" in done.stderr
