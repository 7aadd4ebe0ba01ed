"""Alarms over Modbus TCP (docs/alarms.md "In Modbus TCP", docs/register-map.md) against
the running gateway on simulated sensors, end to end: the simulator leans the boom past
its limit, the discrete input goes to 1 only after the on-delay, the coil says it waits
for an acknowledgement, a client acknowledges it by coil (pymodbus), and the value
comes back through the hysteresis.  mbpoll, a second and independent client, reads the
discrete inputs and coils.  A client without the right to write cannot acknowledge.

Expected addresses and codes are written out here from the register map as documented,
not taken from the server's own tables.  Waits are for events (the cache's samples,
the bits read), never for a fixed time.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import struct
import time
from collections.abc import AsyncIterator, Iterator
from typing import Any

import pytest
from pymodbus.client import AsyncModbusTcpClient
from support.harness import running, until
from test_modbus_tcp import Raw, exc, mbpoll_path

from imu_gateway.app import Gateway
from imu_gateway.model import Series, WireProtocol
from imu_gateway.simulator import SimSensor, SimulatorThread, make_sensor, simulated
from imu_gateway.simulator.motion import Motion

FAST = 115200
ON_DELAY = 1.0
BOOM, MAST, DIAG = 1, 2, 255  # unit ids
# The register map as documented (docs/register-map.md).
ALARM_REGS, ALARM_WORDS = 300, 11  # count, active, unacked, 4 words of each mask
ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE = 0x01, 0x02, 0x03
COIL_ON = 0xFF00


def config(line: str, **modbus: Any) -> dict[str, Any]:
    """The boom (unit 1) with two alarms, the mast (unit 2) with none: three bits on
    unit 1 (boom_lean, boom_low, communication), one on unit 2 (communication)."""
    lean = {"name": "boom_lean", "field": "tilt", "above": 5.0, "hysteresis": 0.5,
            "on_delay_s": ON_DELAY, "severity": "warning"}
    low = {"name": "boom_low", "field": "pitch", "below": -60.0}  # never crossed here
    return {
        "gateway_id": "modbus-alarms",
        "buses": [{"name": "a", "port": line, "baudrate": FAST, "protocol": "native",
                   "timeout_ms": 300, "sensors": [
                       {"name": "boom", "series": "AH", "address": 0, "unit_id": BOOM,
                        "poll_hz": 20, "alarms": [lean, low]},
                       {"name": "mast", "series": "VG", "address": 1, "unit_id": MAST}]}],
        "modbus": {"listen": "127.0.0.1:0", **modbus}}


@contextlib.contextmanager
def two_sensors() -> Iterator[tuple[SimulatorThread, SimSensor]]:
    boom = make_sensor(WireProtocol.NATIVE, Series.AH, 0, baud=FAST,
                       source=Motion.from_seed(7))
    mast = make_sensor(WireProtocol.NATIVE, Series.VG, 1, baud=FAST,
                       source=Motion.from_seed(8))
    with simulated([boom, mast]) as sim:
        sim.call(boom.lean, 1.0, 0.0).result(5)
        yield sim, boom


def port_of(gw: Gateway) -> int:
    assert gw.modbus is not None
    return gw.modbus.port


@contextlib.asynccontextmanager
async def client(gw: Gateway) -> AsyncIterator[AsyncModbusTcpClient]:
    modbus = AsyncModbusTcpClient("127.0.0.1", port=port_of(gw), timeout=5, retries=0)
    assert await modbus.connect()
    try:
        yield modbus
    finally:
        modbus.close()


async def discrete(modbus: AsyncModbusTcpClient, unit: int = BOOM, count: int = 3) -> list[int]:
    rr = await modbus.read_discrete_inputs(0, count=count, device_id=unit)
    assert not rr.isError(), rr
    return [int(b) for b in rr.bits[:count]]


async def coils(modbus: AsyncModbusTcpClient, unit: int = BOOM, count: int = 3) -> list[int]:
    rr = await modbus.read_coils(0, count=count, device_id=unit)
    assert not rr.isError(), rr
    return [int(b) for b in rr.bits[:count]]


async def alarm_registers(modbus: AsyncModbusTcpClient, unit: int = BOOM) -> list[int]:
    rr = await modbus.read_input_registers(ALARM_REGS, count=ALARM_WORDS, device_id=unit)
    assert not rr.isError(), rr
    return list(rr.registers)


def words(count: int, active: int, unacked: int) -> list[int]:
    """The alarm registers for masks of fewer than 16 alarms (word 0 of each mask)."""
    return [count, bin(active).count("1"), bin(unacked).count("1"),
            active, 0, 0, 0, unacked, 0, 0, 0]


async def mbpoll_bits(port: int, unit: int, kind: str, count: int) -> list[int]:
    """mbpoll's reading of discrete inputs (``-t 1``) or coils (``-t 0``) from
    address 0 (its reference 1)."""
    proc = await asyncio.create_subprocess_exec(
        mbpoll_path(), "-m", "tcp", "-p", str(port), "-a", str(unit), "-r", "1",
        "-c", str(count), "-t", kind, "-1", "127.0.0.1",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
    out, err = await asyncio.wait_for(proc.communicate(), 20)
    assert proc.returncode == 0, (out.decode(), err.decode())
    found = {int(m[1]): int(m[2]) for m in re.finditer(r"^\[(\d+)\]:\s+(\d+)\s*$",
                                                      out.decode(), re.MULTILINE)}
    assert sorted(found) == list(range(1, count + 1)), out.decode()
    return [found[ref] for ref in sorted(found)]


async def lean(gw: Gateway, sim: SimulatorThread, boom: SimSensor, pitch: float) -> float:
    """Lean the boom and wait for the first sample of it in the gateway; returns that
    sample's time (wall clock, as the alarm's delays are reckoned from it)."""
    sim.call(boom.lean, pitch, 0.0).result(5)

    def leaned() -> bool:
        reading = gw.cache.snapshot("boom").reading
        return reading is not None and reading.angles is not None \
            and reading.angles.pitch == pitch
    await until(leaned)
    stamp = gw.cache.snapshot("boom").timestamp
    assert stamp is not None
    return stamp.timestamp()


async def samples_pass(gw: Gateway, n: int = 5) -> None:
    seq = gw.cache.snapshot("boom").seq
    await until(lambda: gw.cache.snapshot("boom").seq >= seq + n)


@pytest.mark.anyio
async def test_a_lean_raises_the_discrete_input_after_its_on_delay_and_a_coil_acknowledges(
) -> None:
    with two_sensors() as (sim, boom):
        async with running(config(sim.path, allow_writes=True)) as gw, client(gw) as modbus:
            await samples_pass(gw)
            port = port_of(gw)
            assert await mbpoll_bits(port, BOOM, "1", 3) == [0, 0, 0]
            assert await mbpoll_bits(port, BOOM, "0", 3) == [0, 0, 0]
            assert await alarm_registers(modbus) == words(3, 0, 0)
            assert await alarm_registers(modbus, MAST) == words(1, 0, 0)

            # Beyond the limit (a tilt of 7.5°): not active before the on-delay is over.
            first = await lean(gw, sim, boom, 7.5)
            before = await discrete(modbus)
            if time.time() - first < ON_DELAY:  # (read before the delay ended: must be 0)
                assert before == [0, 0, 0]
            await until(lambda: discrete_is(modbus, [1, 0, 0]), 10)
            assert time.time() - first >= ON_DELAY
            assert await coils(modbus) == [1, 0, 0]  # waits for an acknowledgement
            assert await alarm_registers(modbus) == words(3, 0b001, 0b001)
            assert await mbpoll_bits(port, BOOM, "1", 3) == [1, 0, 0]  # mbpoll -t 1
            assert await mbpoll_bits(port, BOOM, "0", 3) == [1, 0, 0]
            raised = gw.alarm_journal()[-1]
            assert (raised.alarm, raised.to_state.value, raised.value) == \
                ("boom_lean", "active_unacked", 7.5)

            # Acknowledged by coil: still active, no longer waiting.
            rr = await modbus.write_coil(0, True, device_id=BOOM)
            assert not rr.isError(), rr
            assert await coils(modbus) == [0, 0, 0]
            assert await discrete(modbus) == [1, 0, 0]
            assert await alarm_registers(modbus) == words(3, 0b001, 0)
            acked = gw.alarm_journal()[-1]
            assert (acked.alarm, acked.from_state.value, acked.to_state.value, acked.by) == \
                ("boom_lean", "active_unacked", "active_acked", "modbus 127.0.0.1")
            state = {s.name: s for s in gw.alarm_states() if s.sensor == "boom"}
            assert state["boom_lean"].state.value == "active_acked"

            # Nothing left to acknowledge: 03, and nothing written; 0 does nothing.
            journal = len(gw.alarm_journal())
            rr = await modbus.write_coil(0, True, device_id=BOOM)
            assert rr.isError() and rr.exception_code == ILLEGAL_VALUE
            rr = await modbus.write_coil(1, True, device_id=BOOM)  # boom_low: normal
            assert rr.isError() and rr.exception_code == ILLEGAL_VALUE
            assert not (await modbus.write_coil(0, False, device_id=BOOM)).isError()
            assert len(gw.alarm_journal()) == journal

            # Back to 4.6°: within the hysteresis (it clears at 4.5), still active.
            await lean(gw, sim, boom, 4.6)
            await samples_pass(gw)
            assert await discrete(modbus) == [1, 0, 0]
            # 4.4°: through it, the alarm clears (acknowledged already: normal).
            await lean(gw, sim, boom, 4.4)
            await until(lambda: discrete_is(modbus, [0, 0, 0]))
            assert await coils(modbus) == [0, 0, 0]
            assert await alarm_registers(modbus) == words(3, 0, 0)
            assert gw.alarm_journal()[-1].to_state.value == "normal"


async def discrete_is(modbus: AsyncModbusTcpClient, want: list[int]) -> bool:
    return await discrete(modbus) == want


@pytest.mark.anyio
async def test_without_allow_writes_a_coil_cannot_acknowledge() -> None:
    """From the side of a client on a gateway whose Modbus writes are off (the
    default): it reads the alarm, its acknowledgement is refused with 01, and the
    alarm still waits for a person with the right."""
    with two_sensors() as (sim, boom):
        async with running(config(sim.path)) as gw, client(gw) as modbus:
            await lean(gw, sim, boom, 7.5)
            await until(lambda: discrete_is(modbus, [1, 0, 0]), 10)
            journal = len(gw.alarm_journal())
            for value in (True, False):
                rr = await modbus.write_coil(0, value, device_id=BOOM)
                assert rr.isError() and rr.exception_code == ILLEGAL_FUNCTION
            raw = await Raw.connect(port_of(gw))
            try:  # the same, by hand, to the communication alarm too
                for address in (0, 2):
                    pdu = struct.pack(">BHH", 5, address, COIL_ON)
                    assert await raw.ask(BOOM, pdu) == exc(5, ILLEGAL_FUNCTION)
            finally:
                await raw.close()
            assert await coils(modbus) == [1, 0, 0]
            assert len(gw.alarm_journal()) == journal
            state = {s.name: s for s in gw.alarm_states() if s.sensor == "boom"}
            assert state["boom_lean"].state.value == "active_unacked"


@pytest.mark.anyio
async def test_illegal_addresses_quantities_and_values_get_their_exceptions() -> None:
    with two_sensors() as (sim, _):
        async with running(config(sim.path, allow_writes=True)) as gw:
            await samples_pass(gw)
            raw = await Raw.connect(port_of(gw))

            async def expect(unit: int, pdu: bytes, code: int) -> None:
                assert await raw.ask(unit, pdu) == exc(pdu[0], code), (unit, pdu.hex())
            try:
                for function in (1, 2):
                    read = struct.Struct(">BHH")
                    # 02: beyond the alarms (3 on the boom, 1 on the mast)
                    await expect(BOOM, read.pack(function, 0, 4), ILLEGAL_ADDRESS)
                    await expect(BOOM, read.pack(function, 3, 1), ILLEGAL_ADDRESS)
                    await expect(BOOM, read.pack(function, 2, 2), ILLEGAL_ADDRESS)
                    await expect(MAST, read.pack(function, 1, 1), ILLEGAL_ADDRESS)
                    await expect(BOOM, read.pack(function, 0xFFFF, 1), ILLEGAL_ADDRESS)
                    # 03: quantities outside 1-2000, before the address is looked at
                    for count in (0, 2001, 0xFFFF):
                        await expect(BOOM, read.pack(function, 0, count), ILLEGAL_VALUE)
                    await expect(BOOM, bytes((function, 0, 0, 0)), ILLEGAL_VALUE)  # short
                    # the whole of each unit's alarms, one byte of bits
                    assert await raw.ask(BOOM, read.pack(function, 0, 3)) == \
                        bytes((function, 1, 0))
                    assert await raw.ask(MAST, read.pack(function, 0, 1)) == \
                        bytes((function, 1, 0))
                    # unit 255 (diagnostics) has no alarms
                    await expect(DIAG, read.pack(function, 0, 1), ILLEGAL_FUNCTION)
                coil = struct.Struct(">BHH")
                await expect(BOOM, coil.pack(5, 3, COIL_ON), ILLEGAL_ADDRESS)
                await expect(BOOM, coil.pack(5, 0, 0x1234), ILLEGAL_VALUE)
                await expect(BOOM, coil.pack(5, 9, 0x0001), ILLEGAL_VALUE)  # value first
                await expect(MAST, coil.pack(5, 0, COIL_ON), ILLEGAL_VALUE)  # nothing to ack
                await expect(BOOM, bytes.fromhex("0f00000003010f"), ILLEGAL_FUNCTION)  # FC 15
                # the alarm registers: one block, 300-310
                for function in (3, 4):
                    await expect(BOOM, struct.pack(">BHH", function, 300, 12), ILLEGAL_ADDRESS)
                    await expect(BOOM, struct.pack(">BHH", function, 311, 1), ILLEGAL_ADDRESS)
                    await expect(BOOM, struct.pack(">BHH", function, 299, 2), ILLEGAL_ADDRESS)
                # and the connection still serves
                assert (await raw.ask(BOOM, struct.pack(">BHH", 4, 300, 1)))[:4] == \
                    bytes((4, 2, 0, 3))
            finally:
                await raw.close()
            assert gw.alarm_journal() == []


def test_bits_past_the_first_byte_and_word_are_where_the_map_says() -> None:
    """20 alarms, 9 and 17 active, 17 unacknowledged: FC 02's bytes (bit 0 of byte 0
    is alarm 0) and the masks (word 303 + k holds alarms 16k to 16k + 15)."""
    from imu_gateway.alarms import AlarmState, Severity, State
    from imu_gateway.frontends.modbus.alarms import UnitAlarms

    def state(i: int) -> AlarmState:
        now = {9: State.ACTIVE_ACKED, 17: State.ACTIVE_UNACKED}.get(i, State.NORMAL)
        return AlarmState("s", f"a{i}", "pitch", Severity.WARNING, now, None, None, None,
                          False)
    bits = UnitAlarms([state(i) for i in range(20)])
    assert bits.bits(2, 0, 20) == bytes((0, 0b10, 0b10))
    assert bits.bits(2, 9, 9) == bytes((0b1, 0b1))  # alarms 9 and 17 from address 9
    assert bits.bits(1, 0, 20) == bytes((0, 0, 0b10))
    assert struct.unpack(">11H", bits.registers()) == (
        20, 2, 1, 1 << 9, 1 << 1, 0, 0, 0, 1 << 1, 0, 0)
