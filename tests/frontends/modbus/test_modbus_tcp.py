"""The Modbus TCP server (docs/modbus-tcp.md, issue 4) against real peers.

The gateway runs on simulated sensors of both protocols; the clients are pymodbus's
async client, the ``mbpoll`` command and plain sockets (for the framing: pipelining,
malformed MBAP headers, fuzzing).  Expected values come from the simulator and from
the register map as documented (docs/register-map.md), never from the server's own map
module.  Waits are deadlines on a condition (``until``), never measurements of speed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import random
import re
import shutil
import struct
from collections.abc import AsyncIterator, Awaitable
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException
from support.derived import tilt
from support.harness import FIELDS, GROUP_OF, expected, running, tolerance, until

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import Faults, ModbusSensor, SimSensor, hold, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
PATIENT_MS = 300
READING = Motion.from_seed(3).sample(10.0)
MBAP = struct.Struct(">HHHB")

# The register map's codes and i32 scales (docs/register-map.md), written out here so the
# test does not trust the server's own table.
SCALE = {"angles": 100, "accel": 10000, "gyro": 100, "mag": 100000, "quaternion": 1000000}
SERIES_CODE = {Series.IMU: 1, Series.VG: 2, Series.AH: 3, Series.MINS: 4}
PROTOCOL_CODE = {WireProtocol.NATIVE: 0, WireProtocol.MODBUS: 1}
INT32_MIN = -(2**31)
ONLINE, STALE, BUSY, NO_READING = 1 << 0, 1 << 1, 1 << 2, 1 << 4

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 0x01, 0x02, 0x03, 0x04
BUSY_EXC, GATEWAY_PATH, TARGET_FAILED = 0x06, 0x0A, 0x0B


# ------------------------------------------------------------------ set-up


def sensor(protocol: WireProtocol, series: Series, address: int, **options: Any) -> SimSensor:
    return make_sensor(protocol, series, address, baud=FAST, **options)


def bus(name: str, port: str, protocol: str, sensors: list[dict[str, Any]],
        **extra: Any) -> dict[str, Any]:
    """A bus; its answer timeout is patient unless told otherwise, so that a hiccup of
    this busy machine is not a timeout (these tests are not about the bus master)."""
    return {"name": name, "port": port, "baudrate": FAST, "protocol": protocol,
            "sensors": sensors, "timeout_ms": PATIENT_MS, **extra}


def config(buses: list[dict[str, Any]], **modbus: Any) -> dict[str, Any]:
    return {"gateway_id": "test", "buses": buses,
            "modbus": {"listen": "127.0.0.1:0", **modbus}}


def port_of(gateway: Gateway) -> int:
    assert gateway.modbus is not None
    return gateway.modbus.port


async def has_readings(gateway: Gateway, *names: str, seq: int = 1) -> None:
    await until(lambda: all(gateway.cache.snapshot(n).seq >= seq for n in names))


# ------------------------------------------------------------------ raw Modbus TCP


def adu(tid: int, unit: int, pdu: bytes, protocol: int = 0, length: int | None = None) -> bytes:
    return MBAP.pack(tid, protocol, len(pdu) + 1 if length is None else length, unit) + pdu


def read(function: int, address: int, count: int) -> bytes:
    return struct.pack(">BHH", function, address, count)


def write1(address: int, value: int) -> bytes:
    return struct.pack(">BHH", 6, address, value)


def write_n(address: int, words: list[int], count: int | None = None) -> bytes:
    n = len(words) if count is None else count
    return struct.pack(f">BHHB{len(words)}H", 16, address, n, (2 * n) & 0xFF, *words)


def float_words(value: float) -> list[int]:
    return list(struct.unpack(">HH", struct.pack(">f", value)))


def exc(function: int, code: int) -> bytes:
    return bytes((function | 0x80, code))


class Raw:
    """A Modbus TCP client on a plain socket: every byte is the test's."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.tid = 0

    @classmethod
    async def connect(cls, port: int) -> Raw:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        return cls(reader, writer)

    async def send(self, data: bytes) -> None:
        self.writer.write(data)  # one write: one segment on loopback
        await self.writer.drain()

    async def receive(self, timeout: float = 10.0) -> tuple[int, int, int, bytes]:
        """One answer: transaction id, protocol id, unit id, PDU."""
        header = await asyncio.wait_for(self.reader.readexactly(MBAP.size), timeout)
        tid, protocol, length, unit = MBAP.unpack(header)
        assert 2 <= length <= 254, header.hex()
        pdu = await asyncio.wait_for(self.reader.readexactly(length - 1), timeout)
        return tid, protocol, unit, pdu

    async def ask(self, unit: int, pdu: bytes, timeout: float = 10.0) -> bytes:
        self.tid = (self.tid + 1) & 0xFFFF
        await self.send(adu(self.tid, unit, pdu))
        tid, protocol, got_unit, answer = await self.receive(timeout)
        assert (tid, protocol, got_unit) == (self.tid, 0, unit), (tid, protocol, got_unit)
        return answer

    async def closed_by_server(self, timeout: float = 5.0) -> bool:
        """Whether the server closes the connection within ``timeout`` (answers to
        earlier requests may come first)."""
        async def eof() -> None:
            while await self.reader.read(4096):
                pass
        try:
            await asyncio.wait_for(eof(), timeout)
        except (ConnectionResetError, BrokenPipeError):
            return True
        except TimeoutError:
            return False
        return True

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(OSError):
            await self.writer.wait_closed()


async def expect_exception(raw: Raw, unit: int, pdu: bytes, code: int) -> None:
    answer = await raw.ask(unit, pdu)
    assert answer == exc(pdu[0], code), \
        f"unit {unit} request {pdu.hex()}: want {exc(pdu[0], code).hex()}, got {answer.hex()}"


# ------------------------------------------------------------------ pymodbus client


@contextlib.asynccontextmanager
async def pymodbus_client(port: int) -> AsyncIterator[AsyncModbusTcpClient]:
    client = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=5, retries=0)
    assert await client.connect(), "pymodbus could not connect"
    try:
        yield client
    finally:
        client.close()


async def registers(client: AsyncModbusTcpClient, unit: int, address: int, count: int,
                    function: int = 3) -> list[int]:
    call = client.read_holding_registers if function == 3 else client.read_input_registers
    rr = await call(address, count=count, device_id=unit)
    assert not rr.isError(), f"FC{function:02d} unit {unit} {address}+{count}: {rr}"
    return list(rr.registers)


def floats(client: AsyncModbusTcpClient, words: list[int]) -> list[float]:
    values: list[float] = []
    for i in range(0, len(words), 2):
        value = client.convert_from_registers(words[i:i + 2], client.DATATYPE.FLOAT32)
        assert isinstance(value, int | float), value
        values.append(float(value))
    return values


def int32s(client: AsyncModbusTcpClient, words: list[int]) -> list[int]:
    values: list[int] = []
    for i in range(0, len(words), 2):
        value = client.convert_from_registers(words[i:i + 2], client.DATATYPE.INT32)
        assert isinstance(value, int), value
        values.append(value)
    return values


async def error_code(call: Awaitable[Any]) -> int | None:
    rr = await call
    return rr.exception_code if rr.isError() else None


# ------------------------------------------------------------------ mbpoll


def mbpoll_path() -> str:
    path = shutil.which("mbpoll")
    if path is None:
        pytest.fail("mbpoll is not installed: scripts/bootstrap installs it "
                    "(Debian package mbpoll); these tests need a second, independent client")
    return path


async def mbpoll(port: int, unit: int, ref: int, count: int, kind: str) -> dict[int, float]:
    """One poll with mbpoll (run without blocking the loop the gateway runs on);
    ``ref`` is 1-based as mbpoll's -r; returns {ref: value}."""
    proc = await asyncio.create_subprocess_exec(
        mbpoll_path(), "-m", "tcp", "-p", str(port), "-a", str(unit), "-r", str(ref),
        "-c", str(count), "-t", kind, "-B", "-1", "127.0.0.1",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 20)
    assert proc.returncode == 0, (out.decode(), err.decode())
    values = {int(m[1]): float(m[2])
              for m in re.finditer(r"^\[(\d+)\]:\s+(\S+)\s*$", out.decode(), re.MULTILINE)}
    assert len(values) == count, out.decode()
    return values


# ------------------------------------------------------------------ two protocols


@contextlib.asynccontextmanager
async def two_protocols(**modbus: Any) -> AsyncIterator[tuple[Gateway, SimSensor, SimSensor]]:
    """A native AH (unit 1, address 0) and a Modbus VG (unit 2, address 1) on two buses,
    both holding ``READING``."""
    ah = sensor(WireProtocol.NATIVE, Series.AH, 0, source=hold(READING))
    vg = sensor(WireProtocol.MODBUS, Series.VG, 1, source=hold(READING))
    with simulated([ah]) as line_a, simulated([vg]) as line_b:
        cfg = config([
            bus("line-a", line_a.path, "native", [
                {"name": "ah", "series": "AH", "address": 0, "unit_id": 1, "poll_hz": 20}]),
            bus("line-b", line_b.path, "modbus", [
                {"name": "vg", "series": "VG", "address": 1, "unit_id": 2, "poll_hz": 20}]),
        ], **modbus)
        async with running(cfg) as gw:
            await has_readings(gw, "ah", "vg")
            yield gw, ah, vg


UNITS = ((1, WireProtocol.NATIVE, Series.AH, 0), (2, WireProtocol.MODBUS, Series.VG, 1))


@pytest.mark.anyio
async def test_every_register_equals_the_simulator_on_both_protocols() -> None:
    async with two_protocols() as (gw, ah, vg), pymodbus_client(port_of(gw)) as client:
        for (unit, protocol, series, address), sim in zip(UNITS, (ah, vg), strict=True):
            want = expected(sim)
            # floats 100-131: FC03 and FC04 give the same words
            words = await registers(client, unit, 100, 32, 3)
            assert await registers(client, unit, 100, 32, 4) == words
            for name, value in zip(FIELDS, floats(client, words), strict=True):
                if name in want:
                    assert value == pytest.approx(
                        want[name], abs=tolerance(protocol, name, want[name])), name
                else:
                    assert math.isnan(value), (series, name, value)
            # i32 200-231, scaled; the same through FC04
            words = await registers(client, unit, 200, 32, 3)
            assert await registers(client, unit, 200, 32, 4) == words
            for name, value in zip(FIELDS, int32s(client, words), strict=True):
                if name in want:
                    scale = SCALE[GROUP_OF[name]]
                    slack = tolerance(protocol, name, want[name]) * scale + 1
                    assert abs(value - want[name] * scale) <= slack, (name, value)
                else:
                    assert value == INT32_MIN, (series, name, value)
            # a single float read alone equals its place in the block
            pitch = floats(client, await registers(client, unit, 100, 2))[0]
            assert pitch == pytest.approx(want["pitch"], abs=0.005)
            # status 0-8
            status = await registers(client, unit, 0, 9, 3)
            assert status[0] & ONLINE and not status[0] & (STALE | NO_READING), status
            assert status[1] < 65535
            seq = status[2] << 16 | status[3]
            assert seq >= 1
            assert status[6:9] == [SERIES_CODE[series], PROTOCOL_CODE[protocol], address]
            assert (await registers(client, unit, 0, 9, 4))[6:9] == status[6:9]

            async def newer(unit: int = unit, seq: int = seq) -> bool:
                words = await registers(client, unit, 2, 2)
                return (words[0] << 16 | words[1]) > seq
            await until(newer)
        # VG has no magnetometer: NaN and INT32_MIN, checked above; AH has one
        assert "mag_x" in expected(ah) and "mag_x" not in expected(vg)


@pytest.mark.anyio
async def test_derived_values_follow_the_measured_registers() -> None:
    """tilt, tilt_direction and vibration at 132-137 (f32) and 232-237 (i32 × 100,
    × 100, × 10000), after the measured values (docs/register-map.md): the tilt from
    the pitch and roll the same unit serves, the vibration of a sensor held still at
    20 Hz 0 once a second of samples is in (NaN before)."""
    async with two_protocols() as (gw, _, _), pymodbus_client(port_of(gw)) as client:
        for unit, _, _, _ in UNITS:
            async def steady(unit: int = unit) -> bool:
                return floats(client, await registers(client, unit, 136, 2))[0] == 0.0
            await until(steady)
            measured = floats(client, await registers(client, unit, 100, 32, 4))
            pitch, roll = measured[0], measured[1]
            got = floats(client, await registers(client, unit, 132, 6, 4))
            scaled = int32s(client, await registers(client, unit, 232, 6, 3))
            want_tilt, want_direction = tilt(pitch, roll)  # (float32 pitch and roll)
            assert want_direction is not None
            assert got == pytest.approx([want_tilt, want_direction, 0.0], abs=0.011)
            assert scaled[2] == 0
            assert abs(scaled[0] - want_tilt * 100) <= 1.1
            assert abs(scaled[1] - want_direction * 100) <= 1.1


@pytest.mark.anyio
async def test_mbpoll_reads_the_same_values_as_the_simulator() -> None:
    mbpoll_path()  # fails (not skips) when it is missing

    async with two_protocols() as (gw, ah, vg):
        port = port_of(gw)
        for (unit, protocol, series, address), sim in zip(UNITS, (ah, vg), strict=True):
            want = expected(sim)
            holding = await mbpoll(port, unit, 101, 16, "4:float")
            assert await mbpoll(port, unit, 101, 16, "3:float") == pytest.approx(
                holding, nan_ok=True)
            scaled = await mbpoll(port, unit, 201, 16, "4:int")
            for i, name in enumerate(FIELDS):
                value, number = holding[101 + 2 * i], scaled[201 + 2 * i]
                if name not in want:
                    assert math.isnan(value) and number == INT32_MIN, (series, name)
                    continue
                # mbpoll prints six significant digits
                slack = tolerance(protocol, name, want[name]) + 5e-6 * abs(want[name])
                assert value == pytest.approx(want[name], abs=slack), (series, name)
                scale = SCALE[GROUP_OF[name]]
                assert abs(number - want[name] * scale) <= \
                    tolerance(protocol, name, want[name]) * scale + 1, (series, name)
            status = await mbpoll(port, unit, 1, 9, "4")
            assert int(status[1]) & ONLINE
            assert [status[7], status[8], status[9]] == [
                SERIES_CODE[series], PROTOCOL_CODE[protocol], address]


# ------------------------------------------------------------------ exceptions


@pytest.mark.anyio
async def test_exceptions_of_reads_functions_and_units_with_writes_off() -> None:
    async with two_protocols() as (gw, ah, _):
        raw = await Raw.connect(port_of(gw))
        try:
            # 01: writes not allowed; functions the map lacks
            await expect_exception(raw, 1, write1(1000, 1), ILLEGAL_FUNCTION)
            await expect_exception(raw, 1, write_n(1006, float_words(2.0)), ILLEGAL_FUNCTION)
            await expect_exception(raw, 1, bytes.fromhex("0f00000001010f"), ILLEGAL_FUNCTION)
            await expect_exception(raw, 1, bytes.fromhex("050000ff00"), ILLEGAL_FUNCTION)
            await expect_exception(raw, 2, bytes.fromhex("2b0d0100"), ILLEGAL_FUNCTION)
            assert ah.settings.zero_type == "absolute"  # nothing reached the sensor
            # 02: outside the map, across a gap between blocks
            for function in (3, 4):
                await expect_exception(raw, 1, read(function, 9, 1), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, read(function, 50, 2), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, read(function, 0, 10), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, read(function, 136, 4), ILLEGAL_ADDRESS)
                await expect_exception(raw, 2, read(function, 100, 125), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, read(function, 1009, 1), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, read(function, 65535, 1), ILLEGAL_ADDRESS)
            # 03: quantities outside 1-125
            for function in (3, 4):
                for count in (0, 126, 0xFFFF):
                    await expect_exception(raw, 1, read(function, 100, count), ILLEGAL_VALUE)
            # 0A: unknown unit ids
            for unit in (0, 3, 77, 254):  # 255 may be the diagnostics unit
                await expect_exception(raw, unit, read(3, 100, 2), GATEWAY_PATH)
            # and the connection still serves good requests after all of that
            answer = await raw.ask(1, read(3, 100, 2))
            assert answer[:2] == bytes((3, 4))
        finally:
            await raw.close()
        async with pymodbus_client(port_of(gw)) as client:  # the same through pymodbus
            assert await error_code(client.read_holding_registers(
                100, count=2, device_id=77)) == GATEWAY_PATH
            assert await error_code(client.read_input_registers(
                150, count=2, device_id=1)) == ILLEGAL_ADDRESS
            assert await error_code(client.write_register(
                1000, 1, device_id=1)) == ILLEGAL_FUNCTION


@pytest.mark.anyio
async def test_exceptions_of_writes() -> None:
    ah = sensor(WireProtocol.NATIVE, Series.AH, 0, source=hold(READING), save_duration=0.5)
    dead = sensor(WireProtocol.NATIVE, Series.VG, 1, faults=Faults(stalled=True))
    # A Modbus VG the config calls a MINS: the gateway sends MINS commands, and the
    # sensor refuses them with its own exception (the "failure" answer of 04).
    wrong = sensor(WireProtocol.MODBUS, Series.VG, 1, source=hold(READING))
    with simulated([ah, dead]) as line_a, simulated([wrong]) as line_b:
        cfg = config([
            bus("line-a", line_a.path, "native", [
                {"name": "ah", "series": "AH", "address": 0, "unit_id": 1, "poll_hz": 10},
                {"name": "dead", "series": "VG", "address": 1, "unit_id": 2, "poll_hz": 10}]),
            bus("line-b", line_b.path, "modbus", [
                {"name": "mins", "series": "MINS", "address": 1, "unit_id": 3,
                 "poll_hz": 10}]),
        ], allow_writes=True)

        async with running(cfg) as gw:
            await has_readings(gw, "ah", "mins")
            raw = await Raw.connect(port_of(gw))
            try:
                # 02: a command this series lacks; data and unmapped registers
                await expect_exception(raw, 1, write1(1003, 1), ILLEGAL_ADDRESS)  # MINS
                await expect_exception(raw, 1, write1(100, 0), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, write1(0, 0), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, write_n(200, [0, 0]), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, write1(1009, 1), ILLEGAL_ADDRESS)
                await expect_exception(raw, 1, write1(101, 0), ILLEGAL_ADDRESS)
                await expect_exception(raw, 3, write_n(1006, float_words(1.0)),
                                       ILLEGAL_ADDRESS)  # declination is AH only
                # 03: bad values, quantities, half a float
                await expect_exception(raw, 1, write1(1000, 5), ILLEGAL_VALUE)
                await expect_exception(raw, 1, write1(1001, 2), ILLEGAL_VALUE)
                await expect_exception(raw, 1, write1(1008, 4), ILLEGAL_VALUE)
                await expect_exception(raw, 3, write1(1004, 0x42B4), ILLEGAL_VALUE)
                await expect_exception(raw, 1, write1(1006, 0x4000), ILLEGAL_VALUE)
                # a write starting at a float's second half is half a float too
                for unit, address in ((3, 1005), (1, 1005), (1, 1007)):
                    await expect_exception(raw, unit, write1(address, 0), ILLEGAL_VALUE)
                    await expect_exception(raw, unit, write_n(address, [0x42B4, 0]),
                                           ILLEGAL_VALUE)
                await expect_exception(raw, 1, write_n(1006, float_words(math.nan)),
                                       ILLEGAL_VALUE)
                await expect_exception(raw, 1, write_n(1000, [], count=0), ILLEGAL_VALUE)
                # 124 registers cannot be carried in one ADU (253-byte PDU): the
                # quantity field alone must get 03
                await expect_exception(raw, 1, write_n(1000, [], count=124), ILLEGAL_VALUE)
                await expect_exception(raw, 1, write_n(1000, [0] * 4, count=124),
                                       ILLEGAL_VALUE)
                await expect_exception(raw, 1, write_n(1000, [1, 0]), ILLEGAL_VALUE)
                assert ah.settings.zero_type == "absolute"  # none reached the sensor
                # 04: the sensor answered "failure" (its Modbus exception)
                await expect_exception(raw, 3, write1(1003, 1), DEVICE_FAILURE)
                # 0B: a sensor that never answered: reads of values
                status = await raw.ask(2, read(3, 0, 1))
                assert status[:2] == bytes((3, 2))
                bits = int.from_bytes(status[2:4], "big")
                assert bits & NO_READING and not bits & ONLINE, bits
                for function in (3, 4):
                    await expect_exception(raw, 2, read(function, 100, 32), TARGET_FAILED)
                    await expect_exception(raw, 2, read(function, 200, 2), TARGET_FAILED)
                # 04 for a write to it: it was sent, so it may have been carried out
                # ("unconfirmed", docs/modbus-tcp.md), and it is not sent again
                await expect_exception(raw, 2, write1(1000, 1), DEVICE_FAILURE)
                # 06: a command while a save runs
                assert await raw.ask(1, write1(1001, 1)) == write1(1001, 1)
                assert await raw.ask(1, read(3, 1001, 1)) == bytes((3, 2, 0, 1))
                status = await raw.ask(1, read(3, 0, 1))
                assert int.from_bytes(status[2:4], "big") & BUSY
                await expect_exception(raw, 1, write1(1000, 1), BUSY_EXC)
                await expect_exception(raw, 1, write1(1001, 1), BUSY_EXC)
                await expect_exception(raw, 1, write_n(1006, float_words(1.0)), BUSY_EXC)
                # reads are still served from the cache while it saves
                answer = await raw.ask(1, read(4, 100, 32))
                assert answer[:2] == bytes((4, 64))
            finally:
                await raw.close()


@pytest.mark.anyio
async def test_float_commands_take_the_decimal_a_client_meant() -> None:
    """A REAL write of 99.9 is the float32 99.90000153: it is the declination 99.9, the
    limit, and is accepted, as is -99.9; 0.25 is sent as 0.3 (half away from zero, as
    the sensor would show it) and 0.35 (0.3499999940 as float32) as 0.4.  A relative
    heading may be negative (SXXX.YY has a sign)."""
    ah = sensor(WireProtocol.NATIVE, Series.AH, 0, source=hold(READING))
    mins = sensor(WireProtocol.NATIVE, Series.MINS, 1, source=hold(READING))
    with simulated([ah, mins]) as line:
        cfg = config([bus("line", line.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "unit_id": 1, "poll_hz": 5},
            {"name": "mins", "series": "MINS", "address": 1, "unit_id": 2, "poll_hz": 5}])],
            allow_writes=True)

        async with running(cfg) as gw:
            await has_readings(gw, "ah", "mins")
            raw = await Raw.connect(port_of(gw))
            try:
                for written, sent in ((99.9, 99.9), (-99.9, -99.9), (0.25, 0.3),
                                      (-0.25, -0.3), (0.35, 0.4), (12.34, 12.3)):
                    request = write_n(1006, float_words(written))
                    assert await raw.ask(1, request) == request[:5], written
                    assert ah.settings.declination == sent, written
                    readback = await raw.ask(1, read(3, 1006, 2))
                    assert readback == bytes((3, 4)) + struct.pack(">f", sent), written
                await expect_exception(raw, 1, write_n(1006, float_words(99.96)),
                                       ILLEGAL_VALUE)
                await expect_exception(raw, 1, write_n(1006, float_words(100.0)),
                                       ILLEGAL_VALUE)
                assert ah.settings.declination == 12.3
                request = write_n(1004, float_words(-45.5))
                assert await raw.ask(2, request) == request[:5]
                assert await raw.ask(2, read(3, 1004, 2)) == bytes((3, 4)) + \
                    struct.pack(">f", -45.5)
                angles = mins.measure(0.0).angles
                assert angles is not None and angles.yaw == pytest.approx(360 - 45.5)
            finally:
                await raw.close()


@pytest.mark.anyio
async def test_a_write_whose_task_fails_answers_with_the_requests_function_code() -> None:
    """A fault of ours while a write is carried out: exception 04, and the answer's
    function code is the request's with the high bit set (0x86, 0x90), never 0x80."""
    async with two_protocols(allow_writes=True) as (gw, _, _):
        async def broken(*args: Any, **kwargs: Any) -> Any:
            raise RuntimeError("a fault of ours, for the test")
        gw.command = broken  # type: ignore[method-assign]
        raw = await Raw.connect(port_of(gw))
        try:
            assert await raw.ask(1, write1(1000, 1)) == bytes((0x86, DEVICE_FAILURE))
            assert await raw.ask(2, write_n(1000, [1])) == bytes((0x90, DEVICE_FAILURE))
            # the connection goes on
            assert (await raw.ask(2, read(3, 6, 1)))[:2] == bytes((3, 2))
        finally:
            await raw.close()


@pytest.mark.anyio
async def test_sensor_failure_answer_is_exception_04_through_pymodbus() -> None:
    wrong = sensor(WireProtocol.MODBUS, Series.VG, 1, source=hold(READING))
    with simulated([wrong]) as line:
        cfg = config([bus("line", line.path, "modbus", [
            {"name": "mins", "series": "MINS", "address": 1, "poll_hz": 10}])],
            allow_writes=True)

        async with running(cfg) as gw, pymodbus_client(port_of(gw)) as client:
            await has_readings(gw, "mins")
            heading = client.convert_to_registers(90.0, client.DATATYPE.FLOAT32)
            # the VG refuses 0x1E (clear heading) with exception 02: "failure"
            assert await error_code(client.write_register(1003, 1, device_id=1)) == \
                DEVICE_FAILURE
            # 0x1F takes an angle; the VG lacks it too
            assert await error_code(client.write_registers(1004, heading, device_id=1)) \
                == DEVICE_FAILURE


# ------------------------------------------------------------------ pipelining


@pytest.mark.anyio
async def test_pipelined_reads_are_each_answered_in_order() -> None:
    async with two_protocols() as (gw, _, _), pymodbus_client(port_of(gw)) as client:
        requests = [
            (0x1001, 1, read(3, 100, 32)), (0x1002, 2, read(4, 200, 32)),
            (0x1003, 1, read(3, 0, 9)), (0x1004, 2, read(3, 6, 3)),
            (0x1005, 77, read(3, 100, 2)), (0x1006, 1, read(4, 124, 8)),
            (0x1007, 2, read(3, 118, 6)), (0x1008, 1, read(3, 0, 126)),
            (0xFFFF, 2, read(4, 100, 32)), (0x0000, 1, read(3, 218, 6)),
        ]
        want: list[bytes | None] = []
        for _, unit, pdu in requests:  # one at a time, through pymodbus
            function, address, count = struct.unpack(">BHH", pdu)
            if unit == 77:
                want.append(exc(function, GATEWAY_PATH))
            elif count > 125:
                want.append(exc(function, ILLEGAL_VALUE))
            elif address == 0:
                want.append(None)  # status: age and sequence move
            else:
                words = await registers(client, unit, address, count, function)
                want.append(bytes((function, 2 * count)) + struct.pack(
                    f">{count}H", *words))
        raw = await Raw.connect(port_of(gw))
        try:
            for _ in range(3):
                await raw.send(b"".join(adu(t, u, p) for t, u, p in requests))
                for (tid, unit, pdu), answer in zip(requests, want, strict=True):
                    got_tid, protocol, got_unit, got = await raw.receive()
                    assert (got_tid, protocol, got_unit) == (tid, 0, unit)
                    if answer is None:
                        assert got[:2] == bytes((pdu[0], 18))
                        assert got[14:20] == struct.pack(">HHH", SERIES_CODE[Series.AH],
                                                         0, 0)
                    else:
                        assert got == answer, (hex(tid), pdu.hex(), got.hex())
            # many in one segment
            many = [(i, 1 + i % 2, read(3 + i % 2, 100 + 2 * (i % 16), 2))
                    for i in range(60)]
            await raw.send(b"".join(adu(t, u, p) for t, u, p in many))
            for tid, unit, pdu in many:
                got_tid, _, got_unit, got = await raw.receive()
                assert (got_tid, got_unit) == (tid, unit)
                assert got[:2] == bytes((pdu[0], 4))
            # a request split over two segments, then two requests and a half
            frame = adu(7, 1, read(3, 100, 2))
            await raw.send(frame[:5])
            await raw.send(frame[5:] + frame + frame[:9])
            await raw.send(frame[9:])
            for _ in range(3):
                got_tid, _, got_unit, got = await raw.receive()
                assert (got_tid, got_unit, got[:2]) == (7, 1, b"\x03\x04")
        finally:
            await raw.close()


@pytest.mark.anyio
async def test_pipelined_write_then_reads_keep_their_order() -> None:
    async with two_protocols(allow_writes=True) as (gw, ah, vg):
        raw = await Raw.connect(port_of(gw))
        try:
            segment = [
                (1, 2, write1(1000, 1)), (2, 2, read(3, 1000, 1)), (3, 1, read(3, 100, 2)),
                (4, 2, write1(1000, 0)), (5, 2, read(3, 1000, 1)), (6, 2, read(3, 6, 3)),
                (7, 1, write1(1000, 1)), (8, 1, read(4, 1000, 1)),
            ]
            await raw.send(b"".join(adu(t, u, p) for t, u, p in segment))
            answers = [await raw.receive() for _ in segment]
            assert [a[0] for a in answers] == [t for t, _, _ in segment]
            assert [a[2] for a in answers] == [u for _, u, _ in segment]
            pdus = [a[3] for a in answers]
            assert pdus[0] == write1(1000, 1)  # FC06 answers with its request
            assert pdus[1] == bytes((3, 2, 0, 1))  # the write before it is seen
            assert pdus[2][:2] == bytes((3, 4))
            assert pdus[3] == write1(1000, 0)
            assert pdus[4] == bytes((3, 2, 0, 0))
            assert pdus[5] == bytes((3, 6)) + struct.pack(">HHH", 2, 1, 1)
            assert pdus[6] == write1(1000, 1)
            assert pdus[7] == bytes((4, 2, 0, 1))
            assert vg.settings.zero_type == "absolute"
            assert ah.settings.zero_type == "relative"
        finally:
            await raw.close()


# ------------------------------------------------------------------ malformed MBAP


BAD_HEADERS = {
    "protocol id 1": adu(1, 1, read(3, 100, 2), protocol=1),
    "length 0": MBAP.pack(2, 0, 0, 1) + read(3, 100, 2),
    "length 1": MBAP.pack(3, 0, 1, 1) + read(3, 100, 2),
    "length 300": MBAP.pack(4, 0, 300, 1) + bytes(299),
}


async def read_forever(client: AsyncModbusTcpClient, unit: int, stop: asyncio.Event,
                       results: list[bool]) -> None:
    """A well-behaved client: reads the float block until told to stop."""
    while not stop.is_set():
        try:
            rr = await client.read_holding_registers(100, count=32, device_id=unit)
            results.append(not rr.isError() and len(rr.registers) == 32)
        except ModbusException:
            results.append(False)
        await asyncio.sleep(0.005)


@pytest.mark.anyio
async def test_malformed_mbap_closes_that_connection_only() -> None:
    async with two_protocols() as (gw, _, _), pymodbus_client(port_of(gw)) as client:
        port = port_of(gw)
        stop = asyncio.Event()
        results: list[bool] = []
        healthy = asyncio.create_task(read_forever(client, 1, stop, results))
        bystander = await Raw.connect(port)
        try:
            for what, header in BAD_HEADERS.items():
                bad = await Raw.connect(port)
                assert (await bad.ask(2, read(3, 100, 2)))[:2] == b"\x03\x04"
                mark = len(results)
                await bad.send(header)
                assert await bad.closed_by_server(), f"{what}: the connection stayed open"
                await bad.close()
                # the others keep their answers
                assert (await bystander.ask(1, read(4, 200, 2)))[:2] == b"\x04\x04", what

                def grown(mark: int = mark) -> bool:
                    return len(results) > mark + 2

                await until(grown)
        finally:
            stop.set()
            await healthy
            await bystander.close()
        assert results and all(results), results.count(False)
        assert gw.modbus is not None and gw.modbus.listening


# ------------------------------------------------------------------ writes


@pytest.mark.anyio
async def test_writes_reach_the_sensor_and_read_back() -> None:
    async with two_protocols(allow_writes=True) as (gw, ah, vg), \
            pymodbus_client(port_of(gw)) as client:
        # zero type relative through FC06, on both protocols; the answer echoes
        for unit, sim in ((2, vg), (1, ah)):
            rr = await client.write_register(1000, 1, device_id=unit)
            assert not rr.isError(), rr
            assert (rr.address, rr.registers) == (1000, [1])
            assert sim.settings.zero_type == "relative"
            assert await registers(client, unit, 1000, 1) == [1]
            assert await registers(client, unit, 1000, 1, 4) == [1]
        # the relative zero shows in the readings: pitch and roll read 0
        for unit in (1, 2):
            async def zeroed(unit: int = unit) -> bool:
                pitch, roll = floats(client, await registers(client, unit, 100, 4))
                return abs(pitch) < 0.01 and abs(roll) < 0.01
            await until(zeroed)
        # declination as an FC16 float on the native AH
        declination = client.convert_to_registers(3.5, client.DATATYPE.FLOAT32)
        rr = await client.write_registers(1006, declination, device_id=1)
        assert not rr.isError(), rr
        assert (rr.address, rr.count) == (1006, 2)
        assert ah.settings.declination == pytest.approx(3.5, abs=0.005)
        readback = await registers(client, 1, 1006, 2)
        assert floats(client, readback) == [pytest.approx(3.5, abs=0.005)]
        block = await registers(client, 1, 1000, 9)
        assert block[0] == 1 and block[6:8] == readback
        yaw = (READING.angles.yaw + 3.5) % 360.0 if READING.angles else math.nan

        async def turned() -> bool:
            value = floats(client, await registers(client, 1, 104, 2))[0]
            return value == pytest.approx(yaw, abs=0.01)
        await until(turned)
        # the same through the raw bytes: FC16's answer is address and count
        raw = await Raw.connect(port_of(gw))
        try:
            request = write_n(1006, float_words(-1.5))
            assert await raw.ask(1, request) == request[:5]
            assert ah.settings.declination == pytest.approx(-1.5, abs=0.005)
            assert await raw.ask(2, write1(1000, 0)) == write1(1000, 0)
            assert vg.settings.zero_type == "absolute"
            assert await raw.ask(2, read(3, 1000, 1)) == bytes((3, 2, 0, 0))
        finally:
            await raw.close()


@pytest.mark.anyio
async def test_silent_sensor_sets_the_status_bits_then_writes_answer_0b() -> None:
    faults = Faults()
    ah = sensor(WireProtocol.NATIVE, Series.AH, 0, source=hold(READING), faults=faults)
    with simulated([ah]) as line:
        cfg = config([bus("line", line.path, "native", [
            {"name": "ah", "series": "AH", "address": 0, "poll_hz": 20,
             "stale_after_ms": 300}])], allow_writes=True)

        async with running(cfg) as gw, pymodbus_client(port_of(gw)) as client:
            await has_readings(gw, "ah")

            async def status() -> int:
                return (await registers(client, 1, 0, 1))[0]
            assert await status() & ONLINE
            assert await error_code(client.write_register(1000, 0, device_id=1)) is None
            faults.stalled = True
            seen: set[int] = set()

            async def bits(want: int, unset: int) -> bool:
                value = await status()
                seen.add(value)
                return value & want == want and not value & unset
            await until(lambda: bits(0, ONLINE))
            # offline, and its latest reading is older than stale_after_ms: stale
            try:
                await until(lambda: bits(STALE, ONLINE), 5)
                stale_when_offline = True
            except TimeoutError:
                stale_when_offline = False
            offline_bits = sorted(seen)
            age = (await registers(client, 1, 1, 1))[0]
            assert age >= 300
            # the last values are still served; writes get 0B
            assert len(await registers(client, 1, 100, 32)) == 32
            assert await error_code(client.write_register(1000, 1, device_id=1)) == \
                TARGET_FAILED
            declination = client.convert_to_registers(1.0, client.DATATYPE.FLOAT32)
            assert await error_code(client.write_registers(1006, declination,
                                                           device_id=1)) == TARGET_FAILED
            assert ah.settings.zero_type == "absolute"
            faults.stalled = False
            await until(lambda: bits(ONLINE, STALE))
            assert stale_when_offline, (
                f"offline with a reading older than stale_after_ms, but status bit 1 "
                f"(stale) is clear: status values seen {offline_bits}")


# ------------------------------------------------------------------ pass-through


@pytest.mark.anyio
async def test_passthrough_unit_reaches_the_modbus_sensors_own_registers() -> None:
    faults = Faults()
    vg = sensor(WireProtocol.MODBUS, Series.VG, 1, source=hold(READING), faults=faults)
    assert isinstance(vg, ModbusSensor)
    with simulated([vg]) as line:
        cfg = config([bus("line", line.path, "modbus", [
            {"name": "vg", "series": "VG", "address": 1, "unit_id": 2, "raw_unit_id": 50,
             "poll_hz": 10}])], allow_writes=True)

        async with running(cfg) as gw, pymodbus_client(port_of(gw)) as client:
            await has_readings(gw, "vg")

            def own(start: int, count: int) -> list[int]:
                image = vg.registers(0.0)
                return [image[a] for a in range(start, start + count)]
            assert await registers(client, 50, 0x22, 32) == own(0x22, 32)
            assert await registers(client, 50, 0x01, 5) == own(0x01, 5)
            # the sensor's own exceptions come back unchanged
            assert await error_code(client.read_holding_registers(
                0x60, count=1, device_id=50)) == ILLEGAL_ADDRESS
            assert await error_code(client.read_input_registers(
                0x22, count=2, device_id=50)) == ILLEGAL_FUNCTION
            # an FC06 of its own zero-type register (0x0A): relative
            rr = await client.write_register(0x0A, 1, device_id=50)
            assert not rr.isError(), rr
            assert (rr.address, rr.registers) == (0x0A, [1])
            assert vg.settings.zero_type == "relative"
            # what the gateway knows follows, whichever unit set it: its map reads
            # the zero type back (1000: 1 relative)
            assert await registers(client, 2, 1000, 1) == [1]
            assert gw.cache.settings("vg").zero_type == "relative"
            assert await registers(client, 50, 0x05, 1) == own(0x05, 1)
            # a change behind the gateway's back is learnt from a read of 0x05 too
            vg.settings.zero_type = "absolute"
            assert await registers(client, 50, 0x05, 1) == [0]
            assert await registers(client, 2, 1000, 1) == [0]
            vg.settings.zero_type = "relative"
            assert await registers(client, 50, 0x22, 32) == own(0x22, 32)
            # its map unit still works next to it
            assert (await registers(client, 2, 0, 9))[6:9] == [2, 1, 1]
            # a silent sensor: 0B for a read; 04 for a write, which was sent and may
            # have been carried out ("unconfirmed": it is not sent again)
            faults.stalled = True
            assert await error_code(client.read_holding_registers(
                0x22, count=32, device_id=50)) == TARGET_FAILED
            assert await error_code(client.write_register(0x0A, 0, device_id=50)) == \
                DEVICE_FAILURE
            assert vg.settings.zero_type == "relative"


@pytest.mark.anyio
async def test_passthrough_writes_follow_allow_writes() -> None:
    vg = sensor(WireProtocol.MODBUS, Series.VG, 1, source=hold(READING))
    with simulated([vg]) as line:
        cfg = config([bus("line", line.path, "modbus", [
            {"name": "vg", "series": "VG", "address": 1, "raw_unit_id": 50}])])

        async with running(cfg) as gw, pymodbus_client(port_of(gw)) as client:
            assert await error_code(client.write_register(0x0A, 1, device_id=50)) == \
                ILLEGAL_FUNCTION
            assert vg.settings.zero_type == "absolute"
            raw = await Raw.connect(port_of(gw))
            try:
                await expect_exception(raw, 50, read(3, 0x22, 0), ILLEGAL_VALUE)
                await expect_exception(raw, 50, read(3, 0x22, 126), ILLEGAL_VALUE)
                await expect_exception(raw, 50, bytes.fromhex("0100000001"),
                                       ILLEGAL_FUNCTION)
            finally:
                await raw.close()


@pytest.mark.anyio
async def test_passthrough_never_answers_with_another_requests_answer() -> None:
    # The sensor answers after the gateway gave up (answer delay > timeout): each late
    # answer arrives while the next request is on the bus.  A pass-through read of N
    # registers must never come back with the answer to a read of M != N registers.
    vg = sensor(WireProtocol.MODBUS, Series.VG, 1, source=hold(READING), answer_delay=0.15)
    assert isinstance(vg, ModbusSensor)
    with simulated([vg]) as line:
        cfg = config([bus("line", line.path, "modbus", [
            {"name": "vg", "series": "VG", "address": 1, "raw_unit_id": 50,
             "poll_hz": 0.1}], timeout_ms=50, retries=0)])

        async with running(cfg) as gw:
            raw = await Raw.connect(port_of(gw))
            wrong = []
            try:
                for i in range(8):
                    start, count = ((0x22, 32), (0x01, 5), (0x22, 2))[i % 3]
                    answer = await raw.ask(50, read(3, start, count))
                    if answer[0] == 3 and answer[1] != 2 * count:
                        wrong.append((f"03 {start:04x} {count:04x}", answer[:2].hex()))
                    else:
                        assert answer in (exc(3, TARGET_FAILED),
                                          bytes((3, 2 * count)) + struct.pack(
                                              f">{count}H",
                                              *(vg.registers(0.0)[a] for a in
                                                range(start, start + count)))), \
                            answer.hex()
            finally:
                await raw.close()
            assert not wrong, f"pass-through answered (request, answer head): {wrong}"


# ------------------------------------------------------------------ connections


def no_bus(tmp_path: Path, **modbus: Any) -> dict[str, Any]:
    """A gateway whose one bus has no port: the connection rules need no sensor."""
    return config([bus("line", str(tmp_path / "nothing"), "native", [
        {"name": "ah", "series": "AH", "address": 0}])], **modbus)


@pytest.mark.anyio
async def test_clients_outside_allow_from_are_refused_at_connect(tmp_path: Path) -> None:
    async with running(no_bus(tmp_path, allow_from=["10.0.0.0/8"])) as gw:
        raw = await Raw.connect(port_of(gw))
        try:
            with contextlib.suppress(ConnectionError):
                await raw.send(adu(1, 1, read(3, 0, 9)))
            assert await raw.closed_by_server()
        finally:
            await raw.close()


@pytest.mark.anyio
async def test_a_full_server_closes_the_longest_idle_connection_for_a_newcomer(
        tmp_path: Path) -> None:
    async with running(no_bus(tmp_path, max_connections=3)) as gw:
        port = port_of(gw)
        held = await Raw.connect(port)  # never asks: goes first
        first, second = await Raw.connect(port), await Raw.connect(port)
        for raw in (first, second):
            answer = await raw.ask(1, read(3, 6, 3))
            assert answer == bytes((3, 6)) + struct.pack(">HHH", 3, 0, 0)
        third = await Raw.connect(port)
        assert (await third.ask(1, read(3, 6, 1)))[:2] == b"\x03\x02"
        assert await held.closed_by_server()
        fourth = await Raw.connect(port)  # then the one quiet longest
        assert (await fourth.ask(1, read(3, 6, 1)))[:2] == b"\x03\x02"
        assert await first.closed_by_server()
        assert (await second.ask(1, read(3, 6, 1)))[:2] == b"\x03\x02"
        assert gw.modbus is not None and gw.modbus.counts["evicted_limit"] == 2
        for raw in (held, first, second, third, fourth):
            await raw.close()


@pytest.mark.anyio
async def test_one_address_makes_room_among_its_own_connections(tmp_path: Path) -> None:
    async with running(no_bus(tmp_path, max_connections_per_address=2)) as gw:
        port = port_of(gw)
        clients = [await Raw.connect(port) for _ in range(2)]
        for raw in clients:
            await raw.ask(1, read(3, 6, 1))
        newcomer = await Raw.connect(port)
        await newcomer.ask(1, read(3, 6, 1))
        assert await clients[0].closed_by_server()
        assert gw.modbus is not None and gw.modbus.counts["evicted_per_address"] == 1
        for raw in (*clients, newcomer):
            await raw.close()


@pytest.mark.anyio
async def test_idle_connections_time_out(tmp_path: Path) -> None:
    async with running(no_bus(tmp_path, idle_timeout_s=0.5)) as gw:
        raw = await Raw.connect(port_of(gw))
        try:
            assert (await raw.ask(1, read(3, 6, 1)))[:2] == b"\x03\x02"
            assert await raw.closed_by_server(10)
        finally:
            await raw.close()
        again = await Raw.connect(port_of(gw))  # the server itself carries on
        try:
            assert (await again.ask(1, read(3, 6, 1)))[:2] == b"\x03\x02"
        finally:
            await again.close()


# ------------------------------------------------------------------ fuzz


def fuzz_frame(rng: random.Random) -> bytes:
    """A random, or a mutated, Modbus TCP frame."""
    unit = rng.choice([0, 1, 2, 3, 50, 77, 254, 255, rng.randrange(256)])
    function = rng.choice([3, 4, 6, 16, 1, 2, 5, 15, 23, 43, 0x83, 0, rng.randrange(256)])
    address = rng.choice([0, 8, 9, 100, 131, 200, 231, 1000, 1008, rng.randrange(65536)])
    count = rng.choice([0, 1, 2, 32, 125, 126, rng.randrange(65536)])
    if function == 16:
        n = rng.randrange(0, 8)
        pdu = struct.pack(">BHHB", 16, address, count & 0xFFFF, rng.randrange(256)) + \
            rng.randbytes(2 * n)
    else:
        pdu = struct.pack(">BHH", function, address, count)
    pdu = pdu[:rng.randrange(1, len(pdu) + 1)] if rng.random() < 0.2 else pdu
    frame = bytearray(adu(rng.randrange(65536), unit, pdu))
    kind = rng.random()
    if kind < 0.15:  # wholly random bytes
        return rng.randbytes(rng.randrange(1, 300))
    if kind < 0.35:  # flip bytes anywhere, the header included
        for _ in range(rng.randrange(1, 4)):
            i = rng.randrange(len(frame))
            frame[i] = rng.randrange(256)
    elif kind < 0.45:  # a length field that lies
        frame[4:6] = rng.randrange(65536).to_bytes(2, "big")
    elif kind < 0.5:  # a protocol id that is not Modbus
        frame[2:4] = rng.randrange(1, 65536).to_bytes(2, "big")
    elif kind < 0.6:  # cut short
        frame = frame[:rng.randrange(1, len(frame))]
    elif kind < 0.7:  # garbage appended
        frame += rng.randbytes(rng.randrange(1, 40))
    return bytes(frame)


async def fuzzer(port: int, seed: int, frames: int) -> dict[str, int]:
    rng = random.Random(seed)
    counts = {"sent": 0, "closed": 0, "answers": 0}
    raw = await Raw.connect(port)
    try:
        for _ in range(frames):
            batch = b"".join(fuzz_frame(rng) for _ in range(rng.choice([1, 1, 1, 2, 5])))
            try:
                await raw.send(batch)
                counts["sent"] += 1
                while True:  # take whatever answers are already there, never wait
                    data = await asyncio.wait_for(raw.reader.read(65536), 0.001)
                    if not data:
                        raise ConnectionResetError
                    counts["answers"] += 1
            except TimeoutError:
                pass
            except (ConnectionError, OSError):
                counts["closed"] += 1
                await raw.close()
                raw = await Raw.connect(port)
    finally:
        await raw.close()
    return counts


@pytest.mark.anyio
async def test_fuzzed_frames_leave_a_well_behaved_client_served(
        caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="imu_gateway.modbus"):
        async with two_protocols() as (gw, ah, vg), pymodbus_client(port_of(gw)) as client:
            port = port_of(gw)
            stop = asyncio.Event()
            results: list[bool] = []
            good = [asyncio.create_task(read_forever(client, unit, stop, results))
                    for unit in (1, 2)]
            mark = len(results)
            counts = await asyncio.gather(*(fuzzer(port, seed, 80) for seed in range(5)))
            await until(lambda: len(results) > mark + 10)
            stop.set()
            await asyncio.gather(*good)
            assert results and all(results), f"{results.count(False)} of {len(results)} failed"
            assert sum(c["sent"] for c in counts) == 400
            assert sum(c["closed"] for c in counts) > 0  # the fuzz did hit the framing
            # still up and right: a new client gets the simulator's values
            assert gw.modbus is not None and gw.modbus.listening
            async with pymodbus_client(port) as fresh:
                values = floats(fresh, await registers(fresh, 2, 100, 32))
                assert values[0] == pytest.approx(expected(vg)["pitch"], abs=1e-4)
            assert ah.settings.zero_type == "absolute"  # writes were refused throughout
    errors = [r.getMessage() for r in caplog.records
              if r.name.startswith("imu_gateway.modbus") and r.levelno >= logging.ERROR]
    assert not errors, errors
