"""Turning a simulated sensor's heading (docs/simulator.md, "Turning a sensor"): the
Earth's field turns in the sensor's frame, so mag x against mag y goes round a circle;
in the process (``sensor.turn``) and through the ``--control`` socket, read back over
real pseudo-terminals and decoded as the gateway decodes them."""

from __future__ import annotations

import math
import time
from pathlib import Path

import pytest
import serial
from test_lean import control, folder, native_values, simulator  # noqa: F401 (a fixture)

from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import make_sensor, simulated
from imu_gateway.simulator.control import execute
from imu_gateway.simulator.motion import MAG_NORTH, Motion, Turned


def direction(mag_x: float, mag_y: float) -> float:
    """Where north is seen in the sensor's frame: atan2(mag_y, mag_x), degrees [0, 360)."""
    return math.degrees(math.atan2(mag_y, mag_x)) % 360.0


def test_a_level_sensor_turned_sees_north_go_round_against_its_heading() -> None:
    turned = Turned(Motion(roll_amp=0.0, pitch_amp=0.0), yaw0=30.0, rate=90.0, since=10.0)
    for t in (10.0, 10.5, 11.0, 12.0, 13.5):
        reading = turned.sample(t)
        assert reading.angles is not None and reading.mag is not None
        yaw = (30.0 + 90.0 * (t - 10.0)) % 360
        assert reading.angles.yaw == pytest.approx(yaw)
        assert direction(reading.mag.x, reading.mag.y) == pytest.approx((-yaw) % 360, abs=1e-6)
        assert math.hypot(reading.mag.x, reading.mag.y) == pytest.approx(MAG_NORTH)
        assert reading.gyro is not None and reading.gyro.z == pytest.approx(90.0)


def test_turn_takes_the_heading_keeps_the_lean_and_off_gives_the_motion_back() -> None:
    motion = Motion(yaw0=10.0, yaw_rate=2.0)
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH, source=motion)
    sensor.lean(5.0, -4.0)
    sensor.turn(200.0, 0.0, 50.0)
    angles = sensor.measure(51.0).angles
    assert angles is not None and (angles.pitch, angles.roll, angles.yaw) == (5.0, -4.0, 200.0)
    sensor.turn(None)
    angles = sensor.measure(51.0).angles
    assert angles is not None and angles.yaw == pytest.approx(motion.yaw(51.0))
    with pytest.raises(ValueError, match="a turn's rate is a number of degrees"):
        sensor.turn(0.0, math.inf, 0.0)
    assert sensor.turning is None  # as it was


def test_a_turning_sensor_read_over_the_pty_goes_round() -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH)
    with simulated([sensor]) as sim, serial.Serial(sim.path, 9600, timeout=2) as port:
        sim.call(sensor.lean, 0.0, 0.0).result(5)
        sim.call(sensor.turn, 0.0, 120.0, time.monotonic()).result(5)
        seen: set[int] = set()
        deadline = time.monotonic() + 20
        while len(seen) < 36 and time.monotonic() < deadline:
            values, _, _ = native_values(port, 0)
            seen.add(int(direction(values["mag_x"], values["mag_y"]) // 10))
        assert len(seen) == 36  # every 10° of the circle


def test_the_control_socket_turns_a_sensor_from_another_process(folder: Path) -> None:  # noqa: F811
    path = folder / "sim"
    with simulator("--sensor", "native:AH:1", "--control", str(path)) as (proc, pty), \
            serial.Serial(pty, 9600, timeout=2) as port:
        done = control(path, "turn", "1", "123.45")
        assert (done.returncode, done.stdout, done.stderr) == (0, "ok\n", "")
        assert native_values(port, 1)[0]["yaw"] == 123.45
        bad = control(path, "turn", "1", "north")
        assert bad.returncode == 2
        assert "HEADING must be a number of degrees from -3600 to 3600, not 'north'" \
            in bad.stderr
        assert control(path, "turn", "native:1", "off").stdout == "ok\n"
        assert native_values(port, 1)[0]["yaw"] != 123.45
    assert proc.returncode == 0


@pytest.mark.parametrize(("line", "reason"), [
    ("turn 0 10 fast", "RATE must be a number of degrees from -3600 to 3600, not 'fast'"),
    ("turn 0", "turn takes ADDRESS HEADING [RATE] or ADDRESS off, not '0'"),
    ("turn 0 1 2 3", "turn takes ADDRESS HEADING [RATE] or ADDRESS off"),
    ("turn 7 off", "no sensor at address 7"),
])
def test_bad_turns_are_answered_with_the_reason(line: str, reason: str) -> None:
    sensor = make_sensor(WireProtocol.NATIVE, Series.AH)
    answer = execute([sensor], line, now=1.0)
    assert answer.startswith("error: ") and reason in answer, answer
    assert sensor.turning is None
    assert execute([sensor], "turn 0 90 45", now=2.0) == "ok"
    assert sensor.turning == Turned(sensor.source, 90.0, 45.0, 2.0)
