"""``imu-gateway decode`` and ``imu-gateway simulate`` as a user runs them: subprocesses."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import serial

from imu_gateway.protocol import modbus_rtu as rtu
from imu_gateway.protocol import native

AH_215 = (
    "77 38 00 59 10 13 15 00 25 58 02 51 87 10 18 07 10 28 16 01 02 65 10 06 48 01 24 13 00 03"
    " 88 01 59 62 01 63 91 14 14 58 10 22 83 75 10 18 33 49 10 16 55 78 00 93 99 14 58"
)


def cli(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "imu_gateway", *args], capture_output=True,
                          text=True, timeout=timeout, check=False)


def test_decode_data_answer_is_the_reading_json_groups() -> None:
    done = cli("decode", AH_215)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == {
        "angles": {"pitch": -13.15, "roll": 25.58, "yaw": 251.87},
        "accel": {"x": -0.1807, "y": -0.2816, "z": 1.0265},
        "gyro": {"x": -6.48, "y": 124.13, "z": 3.88},
        "mag": {"x": 0.15962, "y": 0.16391, "z": -0.41458},
        "quaternion": {"q0": -0.228375, "q1": -0.183349, "q2": -0.165578, "q3": 0.939914},
    }


def test_decode_several_frames_one_line_each_with_command_frames() -> None:
    done = cli("decode", "77 05 00 0B 02 12", "77 05 00 8D FF 91", "7704000105")
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in done.stdout.splitlines()]
    assert lines == [
        {"command": "set_baudrate", "direction": "request", "address": 0, "section": "2.4",
         "fields": {"baudrate": 9600}},
        {"command": "read_zero_type", "direction": "answer", "address": 0, "section": "2.9",
         "fields": {"zero_type": "relative"}},
        {"command": "read_pitch", "direction": "request", "address": 0, "section": "2.1",
         "fields": {}},
    ]


def test_decode_modbus_answer_in_light_of_its_request_or_start() -> None:
    answer = "01 03 0C DE E4 37 3C E1 7D D5 3C D9 93 7C 3F C0 2C"
    expected = {"accel": {"x": 0.011224, "y": 0.026061, "z": 0.986631}}
    with_request = cli("decode", "--protocol", "modbus", "01 03 00 28 00 06 45 C0", answer)
    assert [json.loads(x) for x in with_request.stdout.splitlines()][1] == expected
    with_start = cli("decode", "--start", "0x28", answer)
    assert json.loads(with_start.stdout) == expected
    angles = cli("decode", "--start", "1", "01 03 04 50 A7 4C EE EE 5C")
    assert json.loads(angles.stdout) == {"angles": {"pitch": 6.47, "roll": -3.06}}


def test_decode_series_drops_what_it_does_not_measure_and_refuses_foreign_frames() -> None:
    block = rtu.encode(rtu.ReadResponse(1, (0,) * rtu.FLOAT_BLOCK_COUNT)).hex()
    vg = cli("decode", "--series", "VG", "--start", "0x22", block)
    assert vg.returncode == 0, vg.stderr
    assert set(json.loads(vg.stdout)) == {"angles", "accel", "gyro", "quaternion"}
    refused = cli("decode", "--series", "VG", AH_215)
    assert refused.returncode == 2
    assert "AH, not VG" in refused.stderr.replace("from AH", "AH")


@pytest.mark.parametrize(("frame", "reason"), [
    ("77 07 00 81 10 34 63 2E", "BadChecksum"),
    ("77 07 00 81 1A 34 63 39", "BadBcd"),
    ("77 08 00 81 10 34 63 2F", "BadLength"),
    ("77 05 00 EE 00 F3", "UnknownFrame"),
    ("01 06 00 0F 00 00 00 B9 C9", "BadChecksum"),  # the Modbus document's save typo
    ("hello", "not a hex string"),
])
def test_decode_bad_frame_exits_2_with_reason(frame: str, reason: str) -> None:
    done = cli("decode", frame)
    assert done.returncode == 2
    assert done.stdout == ""
    assert reason in done.stderr
    assert "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_decode_good_frames_still_print_when_one_is_bad() -> None:
    done = cli("decode", "77 07 00 81 10 34 63 2F", "77 07 00 81 10 34 63 2E")
    assert done.returncode == 2
    assert json.loads(done.stdout) == {"angles": {"pitch": -34.63}}
    assert "frame 2" in done.stderr


@pytest.mark.parametrize("args", [
    ["decode", "--series", "XYZ", "77 04 00 01 05"],
    ["decode", "--start", "-3", "77 04 00 01 05"],
    ["simulate", "--protocol", "native"],
    ["simulate", "--protocol", "can", "--series", "AH"],
    ["simulate", "--sensor", "native:AH:0:1234"],
    ["simulate"],
    ["nonsense"],
])
def test_bad_arguments_exit_2_with_one_clear_error(args: list[str]) -> None:
    done = cli(*args)
    assert done.returncode == 2
    assert "Traceback" not in done.stderr
    assert "error:" in done.stderr


def test_simulate_prints_pty_first_and_stops_cleanly_on_sigint() -> None:
    with subprocess.Popen(
        [sys.executable, "-m", "imu_gateway", "simulate", "--protocol", "native", "--series", "AH",
         "--sensor", "modbus:VG:3"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    ) as proc:
        assert proc.stdout is not None
        first = proc.stdout.readline().split()
        assert first[0] == "PTY" and first[1].startswith("/dev/pts/")
        with serial.Serial(first[1], 9600, timeout=1) as port:
            port.write(native.encode_request("read_all"))
            answer = native.decode(port.read(57))
            assert answer.name == "read_all" and -90 <= answer.values["pitch"] <= 90
            port.write(native.encode_request("set_output_rate", rate_hz=0))  # a write
            assert len(port.read(6)) == 6
        proc.send_signal(signal.SIGINT)
        try:
            assert proc.wait(10) == 0, proc.stderr.read() if proc.stderr else ""
        finally:
            proc.kill()
        # what the line saw, for whoever drove it
        assert proc.stderr is not None
        said = proc.stderr.read().splitlines()[-1]
        assert said.startswith("simulate: stopped: ")
        seen = json.loads(said.removeprefix("simulate: stopped: "))
        assert seen["overlaps"] == seen["collisions"] == 0 and seen["answer_frames"] == 2
        assert seen["writes_heard"] == {"native:AH@0": {"set_output_rate": 1},
                                        "modbus:VG@3": {}}


def test_decode_bad_read_count_is_one_clear_line() -> None:
    """pymodbus would log its own warning for this; decode says one thing, correctly."""
    frame = rtu.encode(rtu.WriteRegister(1, 1, 0xFFFF)).hex()  # FC06 bytes, then made FC03
    raw = bytes.fromhex("0103" + frame[4:12])
    done = cli("decode", (raw + rtu_crc(raw)).hex())
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "read count 65535" in done.stderr


def test_decode_answer_with_no_whole_register_keeps_the_registers() -> None:
    one = rtu.encode(rtu.ReadResponse(1, (0x1234,))).hex()
    done = cli("decode", "--start", "0x22", one)  # half a float
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["fields"]["registers"] == [0x1234]


def test_simulate_link_refuses_to_replace_a_file(tmp_path: Path) -> None:
    victim = tmp_path / "precious.txt"
    victim.write_text("keep me")
    done = cli("simulate", "--protocol", "native", "--series", "AH", "--link", str(victim))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "not a symlink" in done.stderr
    assert victim.read_text() == "keep me"
    missing = cli("simulate", "--protocol", "native", "--series", "AH", "--link",
                  str(tmp_path / "no" / "such" / "dir"))
    assert missing.returncode == 2 and "Traceback" not in missing.stderr


def rtu_crc(raw: bytes) -> bytes:
    from pymodbus.framer import FramerRTU

    return FramerRTU.compute_CRC(raw).to_bytes(2, "big")
