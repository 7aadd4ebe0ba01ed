"""``imu-gateway init`` as a process: from questions on a piped stdin, from a scan of
the simulator on a pty, and the shipped examples; and each result through
``imu-gateway check-config``, which must pass it with no warning but the one about a
port that is not on this machine (an adapter not plugged in here)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated
from imu_gateway.tools.init import examples

ROOT = Path(__file__).resolve().parents[2]
#: the secrets the examples take from the environment
ENV = {"HTTP_TOKEN": "t", "MQTT_PASSWORD": "p", "OPCUA_PASSWORD": "o"}


def cli(*args: str, stdin: str = "", cwd: Path | None = None
        ) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "imu_gateway", *args], input=stdin,
                          capture_output=True, text=True, timeout=120, check=False, cwd=cwd,
                          env={"PATH": "/usr/bin:/bin", **ENV})


def checked(path: Path) -> list[str]:
    """check-config's lines for ``path``, which must pass with no warning but an
    absent port's."""
    done = cli("check-config", "-c", str(path))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    warnings = [line for line in lines if line.startswith("warning:")
                and "does not exist now" not in line]
    assert warnings == [], done.stdout
    return lines


def test_init_from_questions_on_a_piped_stdin(tmp_path: Path) -> None:
    # an empty line takes the default; a bad answer is said and asked again
    answers = ["lab-2", "/dev/imu-line-b", "modbsu", "modbus", "19200", "2",
               "VG", "", "",             # sensor 1: VG at the default address 1, named vg1
               "imu", "300", "7", "motion",  # sensor 2: 300 is out of range, asked again
               "mqtt://broker.lan:1883"]
    done = cli("init", "-o", "g.yaml", stdin="\n".join(answers) + "\n", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "native or modbus, not 'modbsu'" in done.stdout
    assert "1-247, not '300'" in done.stdout
    written = (tmp_path / "g.yaml").read_text()
    assert written.startswith("# A starter config written by `imu-gateway init`")
    lines = checked(tmp_path / "g.yaml")
    assert lines[:3] == [
        "config OK: gateway lab-2, 1 bus, 2 sensors; interfaces: modbus, mqtt, http",
        "sensor vg1 (VG) on line-a: modbus address 1, Modbus TCP unit 1",
        "sensor motion (IMU) on line-a: modbus address 7, Modbus TCP unit 2"]
    bus = yaml.safe_load(written)["buses"][0]
    assert (bus["port"], bus["baudrate"]) == ("/dev/imu-line-b", 19200)
    # the small box's setting, commented out, is one to take as it is
    small = tmp_path / "small.yaml"
    small.write_text(written.replace("# hand_over_ms: 20", "hand_over_ms: 20"))
    assert yaml.safe_load(small.read_text())["hand_over_ms"] == 20
    checked(small)


def test_init_yes_takes_the_defaults_and_never_overwrites_without_force(
        tmp_path: Path) -> None:
    done = cli("init", "--yes", cwd=tmp_path)  # no stdin read
    assert done.returncode == 0, done.stderr
    lines = checked(tmp_path / "gateway.yaml")
    assert lines[:2] == [
        "config OK: gateway gateway-1, 1 bus, 1 sensor; interfaces: modbus, http",
        "sensor ah0 (AH) on line-a: native address 0, Modbus TCP unit 1"]

    (tmp_path / "gateway.yaml").write_text("mine\n")
    refused = cli("init", "--yes", cwd=tmp_path)
    assert refused.returncode == 2
    assert refused.stderr == ("imu-gateway init: error: gateway.yaml exists: give --force "
                              "to overwrite it, or -o another file\n")
    assert (tmp_path / "gateway.yaml").read_text() == "mine\n"
    forced = cli("init", "--yes", "--force", cwd=tmp_path)
    assert forced.returncode == 0, forced.stderr
    checked(tmp_path / "gateway.yaml")


def test_init_from_a_scan_of_the_simulator(tmp_path: Path) -> None:
    sensors = [make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=115200),
               make_sensor(WireProtocol.NATIVE, Series.VG, 5, baud=115200)]
    with simulated(sensors) as sim:
        done = cli("init", "--scan", sim.path, "--protocol", "native", "--baud", "115200",
                   "--gateway-id", "bench", "-o", "g.yaml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    written = (tmp_path / "g.yaml").read_text()
    # the scan cannot tell a native VG from a MINS: the file says so where it matters
    assert "series: VG                # the scan said VG or MINS: set the right one" \
        in written
    lines = checked(tmp_path / "g.yaml")
    assert lines[:3] == [
        "config OK: gateway bench, 1 bus, 2 sensors; interfaces: modbus, http",
        "sensor ah0 (AH) on line-a: native address 0, Modbus TCP unit 1",
        "sensor vg5 (VG) on line-a: native address 5, Modbus TCP unit 2"]
    # the fastest rate that fits 115200 baud
    assert lines[3].startswith("bus line-a at 115200 baud: ah0 10/s (poll), vg5 10/s (poll)")


def test_init_from_a_scan_that_finds_nothing_is_one_clear_error(tmp_path: Path) -> None:
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=9600)]) as sim:
        done = cli("init", "--scan", sim.path, "--protocol", "native", "--baud", "115200",
                   cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.splitlines()[-1].startswith(
        f"imu-gateway init: error: --scan {sim.path}: no sensor answered")
    assert not (tmp_path / "gateway.yaml").exists()


@pytest.mark.parametrize("name", ["single-native", "mixed-bus", "modbus-rtu-only"])
def test_every_shipped_example_passes_check_config_with_no_warning(
        name: str, tmp_path: Path) -> None:
    """The examples live in the package (so the wheel has them: test_install) and
    deploy/examples links to them."""
    assert set(examples()) == {"single-native", "mixed-bus", "modbus-rtu-only"}
    linked = ROOT / "deploy" / "examples" / f"{name}.yaml"
    assert linked.read_text() == examples()[name]
    done = cli("init", "--example", name, "-o", "g.yaml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "g.yaml").read_text() == examples()[name]
    checked(tmp_path / "g.yaml")


def test_init_of_an_unknown_example_names_the_examples(tmp_path: Path) -> None:
    done = cli("init", "--example", "nope", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr == ("imu-gateway init: error: --example nope: no such example (the "
                           "examples: mixed-bus, modbus-rtu-only, single-native)\n")
