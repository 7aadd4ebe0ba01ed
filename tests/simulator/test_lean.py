"""Leaning a simulated sensor on command (docs/simulator.md, "Leaning a sensor"): in the
process (``sensor.lean`` through ``SimulatorThread.call``) and from outside it (the
``--control`` socket and ``imu-gateway simulate-control``), read back over real
pseudo-terminals with pyserial and decoded as the gateway decodes them."""

from __future__ import annotations

import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import serial
from support.harness import interrupt, tolerance

from imu_gateway.model import Series, WireProtocol
from imu_gateway.normalise import field_values
from imu_gateway.protocol import modbus_rtu as rtu
from imu_gateway.protocol import native
from imu_gateway.simulator import make_sensor, simulated
from imu_gateway.simulator.motion import Leaned, Motion

PITCH, ROLL = 7.5, -3.25
CLI = [sys.executable, "-m", "imu_gateway"]


def native_values(port: serial.Serial, address: int) -> tuple[dict[str, float], float, float]:
    """A native read_all (2.15, every group), decoded; and the moments (the simulator's
    clock, which is this one) before the request and after the answer."""
    port.reset_input_buffer()
    before = time.monotonic()
    port.write(native.encode_request("read_all", address))
    answer = bytes(port.read(57))
    after = time.monotonic()
    return dict(native.decode(answer, Series.AH).values), before, after


def modbus_values(port: serial.Serial, unit: int) -> tuple[dict[str, float], float, float]:
    """The angle registers (0x01-0x03, 0.01° steps) and the float32 block (0x22, every
    group), decoded as the gateway decodes them (``read_values``)."""
    values: dict[str, float] = {}
    before = time.monotonic()
    for start, count, name in ((0x01, 3, "angle_"), (rtu.FLOAT_BLOCK_START,
                                                     rtu.FLOAT_BLOCK_COUNT, "")):
        port.reset_input_buffer()
        port.write(rtu.read_request(unit, start, count))
        answer = rtu.decode_frame(bytes(port.read(5 + 2 * count)))
        assert isinstance(answer, rtu.ReadResponse), answer
        values |= {name + k: v for k, v in rtu.read_values(start, answer.registers).items()}
    return values, before, time.monotonic()


def within(value: float, of: Callable[[float], float], before: float, after: float,
           tol: float) -> bool:
    """``value`` is what ``of(t)`` was at some t in [before, after], to ``tol``."""
    seen = [of(before + (after - before) * i / 200) for i in range(201)]
    return min(seen) - tol <= value <= max(seen) + tol


def field_of(motion: Motion, name: str) -> Callable[[float], float]:
    """The motion's value of field ``name`` as a function of time."""
    return lambda t: field_values(motion.sample(t))[name]


def assert_leaned(values: dict[str, float], protocol: WireProtocol, motion: Motion,
                  angle_step: bool = False) -> None:
    """Pitch and roll are the lean's, to the protocol's resolution; so are accel and
    gyro, which depend on nothing else (the gyro: on the motion's steady turn); mag and
    the quaternion are the lean's at the heading read (to that heading's step)."""
    leaned = field_values(Leaned(motion, PITCH, ROLL).sample(0.0))
    for name in ("pitch", "roll", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y",
                 "gyro_z"):
        assert values[name] == pytest.approx(leaned[name],
                                             abs=tolerance(protocol, name, leaned[name])), name
    if angle_step:  # the 0.01° angle registers of a Modbus sensor
        assert values["angle_pitch"] == PITCH and values["angle_roll"] == ROLL
    t = (values["yaw"] - motion.yaw0) / motion.yaw_rate  # when the motion had that heading
    at_yaw = field_values(Leaned(motion, PITCH, ROLL).sample(t))
    for name in ("mag_x", "mag_y", "mag_z", "q0", "q1", "q2", "q3"):
        assert values[name] == pytest.approx(at_yaw[name], abs=2e-4), name


@pytest.mark.parametrize("protocol", [WireProtocol.NATIVE, WireProtocol.MODBUS])
def test_a_lean_shows_in_the_decoded_readings_then_the_motion_again(
        protocol: WireProtocol) -> None:
    motion = Motion(yaw0=10.0, yaw_rate=2.0)  # turns 2°/s: no wrap within the test
    sensor = make_sensor(protocol, Series.AH, source=motion)
    read = native_values if protocol is WireProtocol.NATIVE else modbus_values
    with simulated([sensor]) as sim, serial.Serial(sim.path, 9600, timeout=2) as port:
        assert sim.call(sensor.lean, PITCH, ROLL).result(5) is None
        values, _, _ = read(port, sensor.address)
        assert_leaned(values, protocol, motion, angle_step=protocol is WireProtocol.MODBUS)
        sim.call(sensor.lean, None).result(5)
        values, before, after = read(port, sensor.address)
        for name in ("pitch", "roll"):
            assert within(values[name], field_of(motion, name), before, after,
                          tolerance(protocol, name, 1.0)), (name, values[name])
        assert sim.bus.stats.internal_errors == 0


def test_a_lean_out_of_range_is_refused_and_the_sensor_goes_on() -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH)
    with simulated([sensor]) as sim, serial.Serial(sim.path, 9600, timeout=2) as port:
        sim.call(sensor.lean, PITCH, ROLL).result(5)
        with pytest.raises(ValueError, match="a lean's pitch is a number of degrees from -89 "
                                             "to 89, not 90"):
            sim.call(sensor.lean, 90, 0).result(5)
        values, _, _ = native_values(port, 0)
        assert (values["pitch"], values["roll"]) == (PITCH, ROLL)


# ---------------------------------------------------------------- the control socket


@pytest.fixture
def folder() -> Iterator[Path]:
    """A short folder: a Unix socket's path is at most 107 bytes."""
    with tempfile.TemporaryDirectory(prefix="ctl") as name:
        yield Path(name)


@contextmanager
def simulator(*args: str) -> Iterator[tuple[subprocess.Popen[str], str]]:
    """``imu-gateway simulate ARGS`` in its own process, and its pty; its control socket
    listens once the pty is printed."""
    proc = subprocess.Popen([*CLI, "simulate", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("PTY "), (line, proc.communicate(timeout=10))
        yield proc, line.split()[1]
    finally:
        interrupt(proc)
        proc.communicate()


def control(path: Path, *words: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, "simulate-control", str(path), *words], capture_output=True,
                          text=True, timeout=60)


def test_the_control_socket_leans_each_protocol_from_another_process(folder: Path) -> None:
    path = folder / "sim"
    with simulator("--sensor", "native:AH:1", "--sensor", "modbus:AH:2", "--seed", "4",
                   "--control", str(path)) as (proc, pty), \
            serial.Serial(pty, 9600, timeout=2) as port:
        for address in ("1", "2"):
            done = control(path, "lean", address, str(PITCH), str(ROLL))
            assert (done.returncode, done.stdout, done.stderr) == (0, "ok\n", "")
        assert_leaned(native_values(port, 1)[0], WireProtocol.NATIVE, Motion.from_seed(4))
        assert_leaned(modbus_values(port, 2)[0], WireProtocol.MODBUS, Motion.from_seed(5),
                      angle_step=True)
        assert control(path, "lean", "native:1", "off").stdout == "ok\n"
        values, before, after = native_values(port, 1)
        assert within(values["pitch"], field_of(Motion.from_seed(4), "pitch"), before, after,
                      0.005)
        assert modbus_values(port, 2)[0]["angle_pitch"] == PITCH  # the other one stays
    assert proc.returncode == 0
    assert not path.exists()  # removed on the way out


BAD = [
    # (command line, what the answer must say)
    ("lean native:1 abc 0", "PITCH must be a number of degrees from -89 to 89, not 'abc'"),
    ("lean modbus:1 5 nan", "ROLL must be a number of degrees from -180 to 180, not 'nan'"),
    ("lean native:1 95 0", "PITCH must be a number of degrees from -89 to 89, not '95'"),
    ("lean 9 off", "no sensor at address 9 on this line (it has native:AH@1, modbus:VG@1)"),
    ("lean 1 5 0", "address 1 is native:AH@1 and modbus:VG@1: say native:1 or modbus:1"),
    ("lean one 5 0", "ADDRESS is a bus address such as 1, or native:1 or modbus:1"),
    ("lean canbus:1 off", "ADDRESS is a bus address"),
    ("lean native:1 5", "lean takes ADDRESS PITCH ROLL or ADDRESS off, not 'native:1 5'"),
    ("tilt 1 5 0", "unknown command 'tilt 1 5 0'; the commands are lean ADDRESS PITCH ROLL"),
    ("", "an empty line; the commands are lean ADDRESS PITCH ROLL, lean ADDRESS off"),
    ("\x00\xff\xfe lean", "unknown command"),
]


def converse(path: Path, lines: list[bytes]) -> list[str]:
    """Send ``lines`` on one connection; the answer lines, until the simulator closes."""
    with socket.socket(socket.AF_UNIX) as sock:
        sock.settimeout(30)
        sock.connect(str(path))
        sock.sendall(b"".join(lines))
        sock.shutdown(socket.SHUT_WR)
        got = b""
        while chunk := sock.recv(4096):
            got += chunk
    return got.decode(errors="replace").splitlines()


def test_bad_commands_are_answered_and_the_simulator_goes_on(folder: Path) -> None:
    path = folder / "sim"
    with simulator("--sensor", "native:AH:1", "--sensor", "modbus:VG:1",
                   "--control", str(path)) as (proc, pty), \
            serial.Serial(pty, 9600, timeout=2) as port:
        lines = [line.encode("latin-1") + b"\n" for line, _ in BAD]
        answers = converse(path, [*lines, b"lean native:1 5 -5\n"])
        for (line, reason), answer in zip(BAD, answers, strict=False):
            assert answer.startswith("error: ") and reason in answer, (line, answer)
        assert answers[len(BAD):] == ["ok"]  # the same connection, after every error
        # a line too long for a command: refused, that connection closed, the rest go on
        assert converse(path, [b"lean " + b"9" * 5000 + b"\n", b"lean native:1 6 -6\n"]) \
            == ["error: a command is one line of at most 256 bytes"]
        with socket.socket(socket.AF_UNIX) as gone:  # a client that leaves mid-line
            gone.connect(str(path))
            gone.sendall(b"lean native:1 3 3")  # (say "lean native:1 3 30", cut short)
        refused = control(path, "lean", "9", "5", "0")
        assert refused.returncode == 2 and refused.stdout == ""
        assert refused.stderr == "imu-gateway simulate-control: error: no sensor at address " \
            "9 on this line (it has native:AH@1, modbus:VG@1)\n"
        values, _, _ = native_values(port, 1)
        assert (values["pitch"], values["roll"]) == (5.0, -5.0)  # not the cut line's
        negative = control(path, "lean", "native:1", "-5", "5")  # "-5" is no option
        assert negative.stdout == "ok\n", negative.stderr
        values, _, _ = native_values(port, 1)
        assert (values["pitch"], values["roll"]) == (-5.0, 5.0)
        assert proc.poll() is None
    assert proc.returncode == 0


def test_control_needs_a_free_path_and_says_why_not(folder: Path) -> None:
    taken = folder / "notes.txt"
    taken.write_text("mine")
    done = subprocess.run([*CLI, "simulate", "--protocol", "native", "--series", "AH",
                           "--control", str(taken)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.splitlines() == [
        f"imu-gateway simulate: error: --control {taken}: {taken} exists and is not a "
        "socket; not replacing it"]
    assert taken.read_text() == "mine"
    live = folder / "sim"
    with simulator("--protocol", "native", "--series", "AH", "--control", str(live)):
        second = subprocess.run([*CLI, "simulate", "--protocol", "native", "--series", "AH",
                                 "--control", str(live)], capture_output=True, text=True,
                                timeout=60)
        assert second.returncode == 2
        assert second.stderr.splitlines() == [f"imu-gateway simulate: error: --control "
                                              f"{live}: {live} is the control socket of a "
                                              "running simulator"]
        assert control(live, "lean", "0", "1", "2").stdout == "ok\n"  # the first one's


def test_a_socket_left_by_a_simulator_that_is_gone_is_taken_over(folder: Path) -> None:
    path = folder / "sim"
    left = socket.socket(socket.AF_UNIX)
    left.bind(str(path))  # bound, never listening, then closed: as a killed process leaves it
    left.close()
    with simulator("--protocol", "native", "--series", "AH", "--control", str(path)):
        assert control(path, "lean", "0", "1", "2").stdout == "ok\n"


def test_simulate_control_without_a_simulator_says_so(folder: Path) -> None:
    done = control(folder / "none", "lean", "1", "5", "0")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.splitlines() == [
        f"imu-gateway simulate-control: error: {folder / 'none'}: No such file or directory "
        f"(is 'imu-gateway simulate --control {folder / 'none'}' running?)"]

