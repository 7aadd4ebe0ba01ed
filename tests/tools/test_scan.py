"""The parts of ``imu-gateway scan`` that need no line: the estimate of the time left,
the progress throttle, the address lists, the answers from reserved Modbus units, and
the wording of port errors and of the next-time suggestion."""

from __future__ import annotations

import errno
import time
from collections.abc import Callable
from typing import cast

import pytest
import serial

from imu_gateway.bus.scan import IDENTIFY_TRIES, scan_native
from imu_gateway.model import Series, WireProtocol
from imu_gateway.protocol import modbus_rtu as rtu
from imu_gateway.protocol import native
from imu_gateway.simulator import make_sensor
from imu_gateway.tools.scan import (
    Found,
    Prober,
    Progress,
    ReservedUnitAnswers,
    Step,
    Throttle,
    modbus_units,
    next_time,
    plan,
    port_problem,
    scan_modbus,
    time_left,
)

MARGIN = 0.1


def test_time_left_is_wire_time_plus_margin_of_every_request_still_to_make() -> None:
    steps = plan([WireProtocol.NATIVE, WireProtocol.MODBUS], [9600, 115200])
    c9600, c115200 = 10 / 9600, 10 / 115200
    # Native: the address query, 5 bytes out and 6 back.  Modbus: 8 out, 7 back, each
    # after 3.5 characters of silence and answered after as much again (1.75 ms fast).
    native_9600 = 11 * c9600 + MARGIN
    unit_9600 = 2 * 3.5 * c9600 + 15 * c9600 + MARGIN
    native_115200 = 11 * c115200 + MARGIN
    unit_115200 = 2 * 0.00175 + 15 * c115200 + MARGIN
    later = native_115200 + 247 * unit_115200
    assert time_left(steps, 0, None, MARGIN) == pytest.approx(
        native_9600 + 247 * unit_9600 + later)
    assert time_left(steps, 1, None, MARGIN) == pytest.approx(247 * unit_9600 + later)
    assert time_left(steps, 1, 10, MARGIN) == pytest.approx(10 * unit_9600 + later)
    assert time_left(steps, 3, 1, MARGIN) == pytest.approx(unit_115200)
    # Native addresses are asked one by one (when answers to the query collide) for
    # their zero type: 5 bytes out, 6 back.
    assert time_left(steps, 2, 256, MARGIN) == pytest.approx(
        256 * (11 * c115200 + MARGIN) + 247 * unit_115200)


def test_a_whole_default_scan_is_estimated_at_about_four_minutes() -> None:
    steps = plan(list(WireProtocol), (9600, 115200, 460800, 19200, 38400, 57600, 4800, 2400))
    assert len(steps) == 16
    assert 200 < time_left(steps, 0, None, MARGIN) < 300
    estimates = [time_left(steps, i, None, MARGIN) for i in range(len(steps))]
    assert estimates == sorted(estimates, reverse=True)


def test_progress_lines_say_where_the_scan_is_and_the_time_left() -> None:
    native = Step(WireProtocol.NATIVE, 2400, tuple(range(256)))
    modbus = Step(WireProtocol.MODBUS, 9600, (1, 2, 3))
    assert Progress(native, None, 0, 0.2).line() == \
        "scanning native 2400 baud, address query (about 1 s left)"
    assert Progress(native, 36, 36, 40.2).line() == \
        "scanning native 2400 baud, address 36 (37 of 256; about 41 s left)"
    assert Progress(modbus, None, 0, 245).line() == \
        "scanning modbus 9600 baud, 3 addresses (about 4 min left)"
    assert Progress(Step(WireProtocol.MODBUS, 9600, (5,)), None, 0, 1).line() == \
        "scanning modbus 9600 baud, 1 address (about 1 s left)"
    assert Progress(modbus, 2, 1, 97).line() == \
        "scanning modbus 9600 baud, address 2 (2 of 3; about 1 min 40 s left)"


def test_throttle_passes_every_step_start_and_at_most_one_other_report_a_second() -> None:
    now = [0.0]
    shown: list[Progress] = []
    throttle = Throttle(shown.append, interval=1.0, clock=lambda: now[0])
    step = Step(WireProtocol.MODBUS, 9600, tuple(range(1, 248)))
    throttle(Progress(step, None, 0, 30))
    for asked in range(30):  # eight addresses a second (exact in binary): one report a second
        now[0] += 0.125
        throttle(Progress(step, asked + 1, asked, 30 - asked))
    now[0] += 0.01
    throttle(Progress(Step(WireProtocol.NATIVE, 115200, (0,)), None, 0, 1))  # a new step
    starts = [p for p in shown if p.address is None]
    assert len(starts) == 2
    assert [p.asked for p in shown if p.address is not None] == [7, 15, 23]


def test_modbus_units_are_1_to_247_or_with_all_addresses_up_to_255_never_0() -> None:
    assert modbus_units() == list(range(1, 248))
    assert modbus_units(all_addresses=True) == list(range(1, 256))
    assert modbus_units([0, 250, 3, 3], all_addresses=False) == [3]
    assert modbus_units([0, 250, 3], all_addresses=True) == [3, 250]
    steps = plan([WireProtocol.MODBUS, WireProtocol.NATIVE], [9600], all_addresses=True)
    assert steps[0].addresses == tuple(range(1, 256))
    assert steps[1].addresses == tuple(range(256))


def test_answers_from_a_reserved_unit_are_heard_despite_the_shared_framers_rule() -> None:
    answer = rtu.encode(rtu.ReadResponse(250, (250,)))
    assert rtu.RtuFramer(requests=False).feed(answer) == []  # why the scan has its own
    framer = ReservedUnitAnswers(250)
    assert framer.feed(b"\x00\xff" + answer[:3]) == []  # noise, then half an answer
    assert framer.feed(answer[3:]) == [rtu.ReadResponse(250, (250,))]
    corrupt = answer[:-1] + bytes([answer[-1] ^ 1])
    assert ReservedUnitAnswers(250).feed(corrupt) == []
    assert ReservedUnitAnswers(251).feed(answer) == []


class AnswersAtOnce:
    """Just enough of a serial port for ``Prober``: what a subclass's ``write`` puts in
    ``_unread`` is there to read at once."""

    baudrate = 115200

    def __init__(self) -> None:
        self.timeout = 0.0
        self._unread = bytearray()

    @property
    def in_waiting(self) -> int:
        return len(self._unread)

    def reset_input_buffer(self) -> None:
        self._unread.clear()

    def read(self, size: int = 1) -> bytes:
        data = bytes(self._unread[:size])
        del self._unread[:size]
        return data


class OneReservedSensor(AnswersAtOnce):
    """A Modbus sensor at ``unit`` that answers every read at once (the simulator's
    framing, like the gateway's, drops requests to units above 247, so it cannot play
    this sensor)."""

    def __init__(self, unit: int) -> None:
        super().__init__()
        self.unit = unit
        self.asked: list[int] = []

    def write(self, request: bytes) -> int:
        unit, start, count = request[0], request[2:4], int.from_bytes(request[4:6], "big")
        self.asked.append(unit)
        if unit == self.unit:
            registers = [0] * count
            if start == b"\x00\x04":
                registers[0] = unit  # register 0x04 is the product address
            self._unread += rtu.encode(rtu.ReadResponse(unit, tuple(registers)))
        return len(request)


def test_scan_modbus_finds_a_sensor_at_a_reserved_unit() -> None:
    line = OneReservedSensor(250)
    prober = Prober(cast(serial.Serial, line), margin=0.005)
    found = list(scan_modbus(prober, [249, 250, 251]))
    assert [unit for unit, _ in found] == [250]
    assert line.asked == [249, 250, 250, 251]  # 250 twice: found, then read for its series


class MissesAnAnswer(OneReservedSensor):
    """The sensor of ``OneReservedSensor``, whose answer to the read of its values is
    lost the first ``misses`` times (a busy machine, a late pseudo-terminal)."""

    def __init__(self, unit: int, misses: int) -> None:
        super().__init__(unit)
        self.misses = misses

    def write(self, request: bytes) -> int:
        if request[2:4] != b"\x00\x04" and self.misses > 0:  # (not the address query)
            self.misses -= 1
            self.asked.append(request[0])
            return len(request)
        return super().write(request)


@pytest.mark.parametrize("misses", [1, 2])
def test_a_found_sensor_missing_an_answer_is_asked_again_what_it_is(misses: int) -> None:
    line = MissesAnAnswer(250, misses)
    prober = Prober(cast(serial.Serial, line), margin=0.005)
    [(unit, series)] = list(scan_modbus(prober, [250]))
    assert unit == 250 and series != "unknown", series
    assert line.asked == [250] * (2 + misses)


def test_a_found_sensor_that_never_says_what_it_is_is_unknown() -> None:
    line = MissesAnAnswer(250, misses=100)
    prober = Prober(cast(serial.Serial, line), margin=0.005)
    assert list(scan_modbus(prober, [250])) == [(250, "unknown")]
    assert line.asked == [250] * (1 + IDENTIFY_TRIES)


class CutsAnswers(AnswersAtOnce):
    """A lone native sensor (the simulator's) that answers every request at once, but
    the answers to the requests numbered in ``cut`` (1: the first) come cut short,
    their first half only (a port that handed the rest over after the wait for it),
    and those in ``garbled`` come whole but garbled (as two sensors' answers at once
    do)."""

    def __init__(self, address: int, cut: frozenset[int], garbled: frozenset[int] = frozenset()
                 ) -> None:
        super().__init__()
        self.sensor = make_sensor(WireProtocol.NATIVE, Series.AH, address,
                                  baud=self.baudrate)
        self.cut = cut
        self.garbled = garbled
        self.written: list[bytes] = []

    def write(self, request: bytes) -> int:
        self.written.append(request)
        answer = b"".join(out.frame for out in self.sensor.hear(
            request, time.monotonic(), after_silence=True))
        if len(self.written) in self.cut:
            answer = answer[:len(answer) // 2]
        elif len(self.written) in self.garbled:
            answer = bytes(b ^ 0x5A for b in answer)
        self._unread += answer
        return len(request)


QUERY = native.encode_request("read_address")


def test_a_lone_sensors_answer_to_the_query_cut_short_is_asked_again_not_swept() -> None:
    """The query's answer came in half (no answer, a few bytes: garbled): the query is
    asked once more, and its clean answer finds the sensor with no address asked one by
    one (256 of them: 25 s at the default margin)."""
    line = CutsAnswers(7, cut=frozenset({1}))
    prober = Prober(cast(serial.Serial, line), margin=0.005)
    assert list(scan_native(prober, range(256))) == [(7, "AH")]
    assert line.written[:2] == [QUERY, QUERY] and len(line.written) == 3, line.written


def test_a_query_garbled_twice_asks_every_address() -> None:
    """A lone answer cut short twice: every address is asked, and the sensor is found
    so."""
    line = CutsAnswers(7, cut=frozenset({1, 2}))
    prober = Prober(cast(serial.Serial, line), margin=0.005)
    assert list(scan_native(prober, range(16))) == [(7, "AH")]
    assert line.written[:2] == [QUERY, QUERY] and len(line.written) == 2 + 16 + 1


def test_a_query_garbled_whole_asks_every_address_at_once() -> None:
    """An answer's worth of garbled bytes is what several sensors answering at once
    give: a second query that came clean might miss one of them (silent that time, or
    drowned), so every address is asked, without a second query."""
    line = CutsAnswers(7, cut=frozenset(), garbled=frozenset({1}))
    prober = Prober(cast(serial.Serial, line), margin=0.005)
    assert list(scan_native(prober, range(16))) == [(7, "AH")]
    assert line.written[0] == QUERY and len(line.written) == 1 + 16 + 1, line.written


class TimedLine:
    """Just enough of a serial port for ``Prober``: bytes that come in at their times,
    on the real clock (``due``: the bytes that have come by a time, in order), and
    nobody answering what is ``written``."""

    baudrate = 9600

    def __init__(self, due: Callable[[float], bytes]) -> None:
        self.timeout = 0.0
        self._due = due
        self._start = time.monotonic()
        self._taken = 0
        self.written: list[bytes] = []

    def _now(self) -> bytes:
        return self._due(time.monotonic() - self._start)

    @property
    def in_waiting(self) -> int:
        return len(self._now()) - self._taken

    def reset_input_buffer(self) -> None:
        self._taken = len(self._now())

    def write(self, request: bytes) -> int:
        self.written.append(request)
        return len(request)

    def read(self, size: int = 1) -> bytes:
        end = time.monotonic() + self.timeout
        while not self.in_waiting and time.monotonic() < end:
            time.sleep(0.001)
        data = self._now()[self._taken:self._taken + size]
        self._taken += len(data)
        return data


def test_a_stream_at_another_rate_does_not_send_the_scan_through_every_address() -> None:
    """A line that carries, asked or not, bytes that make no frame at this rate (a
    sensor streaming at another: at 9600, its 115200-baud frames come as a few bytes of
    0x00, 0x80, 0xF8 each, one every 2 ms), and that nobody answers: the query alone."""
    line = TimedLine(lambda t: b"\x00\x80\xf8" * int(t / 0.002))
    prober = Prober(cast(serial.Serial, line), margin=0.005)
    assert list(scan_native(prober, range(256))) == []
    assert line.written == [native.encode_request("read_address")]


def _stream(period: float, phase: float, frame: bytes = b"\x77" + bytes(56)
            ) -> Callable[[float], bytes]:
    """A native stream at this rate: ``frame`` every ``period`` s from ``phase``."""
    char = 10 / TimedLine.baudrate

    def due(t: float) -> bytes:
        if t < phase:
            return b""
        done, into = divmod(t - phase, period)
        return frame * int(done) + frame[:min(len(frame), int(into / char))]

    return due


@pytest.mark.parametrize("period", [0.2, 0.25, 0.4])
@pytest.mark.parametrize("phase", [0.0, 0.05, 0.13])
def test_a_slow_stream_at_this_rate_is_not_taken_for_another_rates(
        period: float, phase: float) -> None:
    """A stream at the scanned rate, frames cut by the listen's start or end wherever
    they fall: its frames are readable here, so the rate is swept as before."""
    prober = Prober(cast(serial.Serial, TimedLine(_stream(period, phase))), margin=0.1)
    assert not prober.unreadable_traffic()


def test_a_collision_ending_late_is_not_taken_for_another_rates_stream() -> None:
    """Two answers to the query that collided and came in late (60 ms of bytes with
    no frame start, ending 100 ms on): nothing more comes, so the rate is swept."""
    def due(t: float) -> bytes:
        return b"\x80\xf8" * int(min(max(t - 0.04, 0.0), 0.06) / 0.002)

    prober = Prober(cast(serial.Serial, TimedLine(due)), margin=0.02)
    assert not prober.unreadable_traffic()


@pytest.mark.parametrize("code", [errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY])
def test_a_busy_port_is_said_to_be_in_use(code: int) -> None:
    # pyserial's own wording for the flock case; EBUSY is what a TIOCEXCL holder gives.
    exc = serial.SerialException(code, f"Could not exclusively lock port /dev/ttyUSB0: "
                                 f"[Errno {code}] Resource temporarily unavailable")
    assert port_problem("/dev/ttyUSB0", exc).startswith(
        "/dev/ttyUSB0 is in use by another process: stop the gateway first (it holds "
        "/dev/ttyUSB0)")


def test_other_port_errors_keep_their_cause_said_once() -> None:
    missing = serial.SerialException(errno.ENOENT, "could not open port /dev/x: [Errno 2] "
                                     "No such file or directory: '/dev/x'")
    assert port_problem("/dev/x", missing).startswith(
        "cannot open /dev/x: No such file or directory")
    denied = serial.SerialException(errno.EACCES, "could not open port /dev/x: ...")
    assert "dialout" in port_problem("/dev/x", denied)
    lost = serial.SerialException("read failed: device reports readiness to read but "
                                  "returned no data")
    assert port_problem("/dev/x", lost) == f"/dev/x: {lost}"


def test_next_time_names_only_the_protocols_and_rates_that_found_something() -> None:
    native = Found(WireProtocol.NATIVE, 115200, 0, "AH")
    modbus = Found(WireProtocol.MODBUS, 9600, 3, "IMU")
    assert next_time("/dev/ttyUSB0", [native]) == \
        "next time: imu-gateway scan --port /dev/ttyUSB0 --protocol native --baud 115200"
    assert next_time("/dev/ttyUSB0", [native, modbus]) == \
        "next time: imu-gateway scan --port /dev/ttyUSB0 --baud 9600 --baud 115200"
    reserved = Found(WireProtocol.MODBUS, 9600, 250, "unknown")
    assert next_time("/dev/my port", [reserved], margin_ms=300) == (
        "next time: imu-gateway scan --port '/dev/my port' --protocol modbus --baud 9600 "
        "--all-addresses --margin-ms 300")
