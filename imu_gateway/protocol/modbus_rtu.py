"""The sensors' Modbus RTU protocol (the vendor's Modbus document), sans-IO.

pymodbus does the Modbus work proper: PDU classes, their encoding, the RTU frame size
of each function code, and the CRC.  What it does not do well for us is *finding*
frames in a byte stream: ``FramerRTU.decode`` (pymodbus 3.16) reports the whole
buffer as used both when a frame is found and when a CRC fails, so a second frame in
the same read (auto-output streams at 500 Hz) is thrown away and a frame behind a
burst of noise is lost with the noise.  ``RtuFramer`` below is a small resync loop
around pymodbus's size and CRC functions: on a bad CRC it drops one byte and looks
again, and it keeps the bytes after a frame.  ``docs/protocol-notes.md`` has the
measurement.

The sensor's quirks (from the document, checked against its examples):

* angle registers 0x01-0x03 hold ``deg * 100 + 20000`` as an unsigned 16-bit value;
* float registers 0x22-0x41 send each float's four bytes **low byte first**
  (``DE E4 37 3C`` is 0.011224): byte order DCBA across the two registers;
* a baud-rate write (0x0B) is not answered and takes effect at once;
* an address write (0x0D) is answered from the **new** address;
* a gyro-calibration write (0x10) is echoed with 0 (started) and, later, an
  unsolicited echo with 1 (done) follows;
* auto-output (0x1B interval in ms, 0x1C start register << 8 | count) makes the
  sensor send FC03 answers on its own.

Library errors are converted to ``errors.FrameError``/``UsageError`` here and nowhere else.
"""

from __future__ import annotations

import enum
import functools
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from pymodbus.exceptions import ModbusException
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU, ModbusPDU
from pymodbus.pdu import ExceptionResponse as PduException
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersRequest,
    ReadInputRegistersResponse,
    WriteMultipleRegistersRequest,
    WriteMultipleRegistersResponse,
    WriteSingleRegisterRequest,
    WriteSingleRegisterResponse,
)

from ..modbus_codes import READ_HOLDING, READ_INPUT, WRITE_MULTIPLE, WRITE_SINGLE
from ..model import KnownSettings, Series, shortest_float32
from .bcd import round_half_away
from .errors import BadChecksum, BadLength, FrameError, UnknownFrame, UsageError
from .native import BAUD_CODES

FUNCTIONS = frozenset({READ_HOLDING, READ_INPUT, WRITE_SINGLE, WRITE_MULTIPLE})
MAX_READ = 125
MAX_WRITE = 123
ANGLE_OFFSET = 20000  # angle registers: raw = deg * 100 + 20000
UNIT_IDS = range(1, 248)  # addressable Modbus devices (0 is broadcast, 248-255 reserved)
GYRO_CAL_STARTED, GYRO_CAL_COMPLETE = 0, 1  # 2.11: what the calibration's echo carries


# --------------------------------------------------------------------------- values


def angle_from_register(raw: int) -> float:
    return (raw - ANGLE_OFFSET) / 100


def angle_to_register(degrees: float) -> int:
    if not math.isfinite(degrees):
        raise UsageError(f"{degrees} deg is not a finite angle")
    raw = round_half_away(degrees, 2) + ANGLE_OFFSET  # as the native BCD angles round
    if not 0 <= raw <= 0xFFFF:
        raise UsageError(f"{degrees} deg does not fit an angle register (-200 to 455.35)")
    return raw


def float_from_registers(first: int, second: int) -> float:
    """Two registers as sent (DE E4, 37 3C) to the float they carry (low byte first).

    The result is the shortest decimal that is the same float32 (0.011224, as the
    document prints it, not 0.011223999783396721): a float32 has about seven digits and
    the rest is noise of the widening to a Python float.
    """
    return shortest_float32(float(struct.unpack("<f", struct.pack(">HH", first, second))[0]))


#: Two registers' four bytes, as sent, read as the float they carry (low byte first).
_DCBA = struct.Struct("<f")


def float_to_registers(value: float) -> tuple[int, int]:
    first, second = struct.unpack(">HH", struct.pack("<f", value))
    return int(first), int(second)


class Kind(enum.Enum):
    """How a sensor register's raw 16-bit content maps to a value."""

    ANGLE = "(raw - 20000) / 100 deg"
    U16 = "unsigned 16-bit"
    FLOAT_DCBA = "float32 over two registers, low byte first"
    ZERO_TYPE = "0 absolute, 1 relative"
    BAUD_CODE = "baud-rate code (the native 2.4 codes; others mean 9600)"
    START_COUNT = "start register << 8 | register count"


class WriteAnswer(enum.Enum):
    """What the sensor sends back after a write, per register (the document's quirks)."""

    ECHO = "echo"
    NONE = "no answer; takes effect at once"
    ECHO_FROM_NEW_ADDRESS = "echo, sent from the new address"
    STARTED_THEN_DONE = "echo of 0 (started), later an echo of 1 (done)"


@dataclass(frozen=True, slots=True)
class SensorRegister:
    name: str
    address: int
    kind: Kind
    writable: bool = False
    answer: WriteAnswer = WriteAnswer.ECHO
    #: values a write accepts, where narrower than the kind's (None: the kind decides)
    accepts: range | None = None
    series: frozenset[Series] = frozenset(Series)
    section: str = "1.2"

    @property
    def count(self) -> int:
        return 2 if self.kind is Kind.FLOAT_DCBA else 1


_FLOAT_FIELDS = (
    "pitch", "roll", "yaw", "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z",
    "mag_x", "mag_y", "mag_z", "q0", "q1", "q2", "q3",
)
FLOAT_BLOCK_START = 0x22
FLOAT_BLOCK_COUNT = 2 * len(_FLOAT_FIELDS)  # one FC03 of 32 registers reads all sixteen
MINS = frozenset({Series.MINS})

# The sensor's register list (document 1.2).  Field names of readable registers are the
# per-field names of the reading JSON (``pitch``, ``accel_x``, ``q0`` …; X-axis angle =
# pitch, Y = roll, Z = yaw).
REGISTERS: tuple[SensorRegister, ...] = (
    SensorRegister("pitch", 0x01, Kind.ANGLE, section="2.1"),
    SensorRegister("roll", 0x02, Kind.ANGLE, section="2.2"),
    SensorRegister("yaw", 0x03, Kind.ANGLE),
    SensorRegister("product_address", 0x04, Kind.U16),
    SensorRegister("zero_type", 0x05, Kind.ZERO_TYPE, section="2.6"),
    SensorRegister("set_zero_type", 0x0A, Kind.ZERO_TYPE, True, section="2.5",
                   accepts=range(2)),
    SensorRegister("set_baudrate", 0x0B, Kind.BAUD_CODE, True, WriteAnswer.NONE, section="2.3"),
    # The document allows 0x00-0xFF; Modbus reserves 0 for broadcast and 248-255, so a
    # sensor given one of those could never be talked to alone: we accept 1-247.
    SensorRegister("set_address", 0x0D, Kind.U16, True, WriteAnswer.ECHO_FROM_NEW_ADDRESS,
                   section="2.7", accepts=UNIT_IDS),
    SensorRegister("save", 0x0F, Kind.U16, True, section="2.4"),
    SensorRegister("calibrate_gyro", 0x10, Kind.U16, True, WriteAnswer.STARTED_THEN_DONE,
                   section="2.11"),
    SensorRegister("output_interval_ms", 0x1B, Kind.U16, True, section="2.12"),
    SensorRegister("output_registers", 0x1C, Kind.START_COUNT, True, section="2.13"),
    # 0x1E/0x1F are listed for MINS without a format: we write 0 to clear the heading and
    # the start point in the angle registers' encoding (docs/protocol-notes.md).
    SensorRegister("clear_heading", 0x1E, Kind.U16, True, series=MINS),
    SensorRegister("set_relative_heading", 0x1F, Kind.ANGLE, True, series=MINS),
    *(
        SensorRegister(name, FLOAT_BLOCK_START + 2 * i, Kind.FLOAT_DCBA, section="2.8-2.10")
        for i, name in enumerate(_FLOAT_FIELDS)
    ),
)
READABLE: tuple[SensorRegister, ...] = tuple(r for r in REGISTERS if not r.writable)
#: Writable registers by name.  (Readable names are not unique: ``pitch`` is both the
#: 0x01 angle register and the 0x22 float, which is why there is no such map for them.)
WRITABLE: Mapping[str, SensorRegister] = MappingProxyType(
    {r.name: r for r in REGISTERS if r.writable}
)
REGISTERS_BY_ADDRESS: Mapping[int, SensorRegister] = MappingProxyType(
    {r.address: r for r in REGISTERS}
)


def encode_value(register: SensorRegister, value: Any) -> int:
    """A value for a writable register to the 16-bit word the sensor expects."""
    kind = register.kind
    if kind is Kind.ANGLE:
        return angle_to_register(float(value))
    if kind is Kind.ZERO_TYPE:
        codes = {"absolute": 0, "relative": 1}
        if value not in codes:
            raise UsageError(f"zero type must be absolute or relative, not {value!r}")
        return codes[value]
    if kind is Kind.BAUD_CODE:
        for code, baud in BAUD_CODES.items():
            if baud == value:
                return code
        raise UsageError(f"baud rate must be one of {sorted(BAUD_CODES.values())}, not {value}")
    if kind is Kind.START_COUNT:
        start, count = value
        if not (0 <= start <= 0xFF and 0 <= count <= 0xFF):
            raise UsageError(f"auto-output start and count are one byte each, not {value}")
        return int(start) << 8 | int(count)
    if not isinstance(value, int) or not 0 <= value <= 0xFFFF:
        raise UsageError(f"{register.name}: {value!r} is not a 16-bit value")
    if register.accepts is not None and value not in register.accepts:
        limits = register.accepts
        raise UsageError(f"{register.name}: {value} is not {limits.start}-{limits.stop - 1}")
    return value


def decode_value(register: SensorRegister, raw: int) -> Any:
    """The inverse of ``encode_value`` for one 16-bit word (floats: see ``read_values``)."""
    kind = register.kind
    if kind is Kind.ANGLE:
        return angle_from_register(raw)
    if kind is Kind.ZERO_TYPE:
        return "relative" if raw else "absolute"
    if kind is Kind.BAUD_CODE:
        return BAUD_CODES.get(raw, 9600)  # "Other indicates 9600"
    if kind is Kind.START_COUNT:
        return (raw >> 8, raw & 0xFF)
    return raw


def read_values(start: int, registers: Sequence[int]) -> dict[str, Any]:
    """The values of every readable register wholly inside a read of ``registers``
    starting at ``start`` ("the answer in the light of its request")."""
    values: dict[str, Any] = {}
    # (the words as sent, once: each float is then read from them in place; a poll
    # answer carries sixteen)
    words = struct.pack(f">{len(registers)}H", *registers)
    for reg, offset in _read_plan(start, len(registers)):
        if reg.kind is Kind.FLOAT_DCBA:
            values[reg.name] = shortest_float32(_DCBA.unpack_from(words, 2 * offset)[0])
        else:
            values[reg.name] = decode_value(reg, registers[offset])
    return values


@functools.lru_cache(maxsize=256)
def _read_plan(start: int, count: int) -> tuple[tuple[SensorRegister, int], ...]:
    """The registers wholly inside a read, with their offsets: worked out once per
    span (a poll reads the same span every time; it was a walk of the whole table per
    answer)."""
    return tuple((reg, reg.address - start) for reg in READABLE
                 if start <= reg.address and reg.address + reg.count <= start + count)


def register_image(values: Mapping[str, Any]) -> dict[int, int]:
    """The sensor side of ``read_values``: register address -> word for the given values
    (the simulator's view of its own register file)."""
    image: dict[int, int] = {}
    for reg in READABLE:
        if reg.name not in values:
            continue
        value = values[reg.name]
        if reg.kind is Kind.FLOAT_DCBA:
            image[reg.address], image[reg.address + 1] = float_to_registers(value)
        else:
            image[reg.address] = encode_value(reg, value)
    return image


#: Sensor registers that show a setting the gateway keeps (``model.KnownSettings``'s
#: fields), read or written: what a pass-through exchange teaches about the sensor.
SETTING_REGISTERS: Mapping[str, str] = MappingProxyType({
    "zero_type": "zero_type", "set_zero_type": "zero_type",
    "set_relative_heading": "relative_heading",
})


def settings_shown(request: bytes, answer: bytes) -> KnownSettings:
    """The settings a pass-through exchange (request and answer PDUs) shows (see
    ``_settings_shown``)."""
    return KnownSettings(**_settings_shown(request, answer))


def _settings_shown(request: bytes, answer: bytes) -> dict[str, Any]:
    """The settings a pass-through exchange (request and answer PDUs) shows: a write
    the sensor acknowledged, or a read of a register that holds one.  A refused or
    malformed exchange shows nothing."""
    if len(request) < 5 or not answer or answer[0] != request[0]:
        return {}  # an exception answer, or not an answer to this request
    function, start = request[0], int.from_bytes(request[1:3], "big")
    words: list[int] = []
    if function in (READ_HOLDING, READ_INPUT):
        if len(answer) < 2 or len(answer) != 2 + answer[1] or answer[1] % 2:
            return {}
        words = [int.from_bytes(answer[i:i + 2], "big") for i in range(2, len(answer), 2)]
        values = read_values(start, words)
        return {SETTING_REGISTERS[k]: v for k, v in values.items() if k in SETTING_REGISTERS}
    if function == WRITE_SINGLE and answer == request:
        words = [int.from_bytes(request[3:5], "big")]
    elif function == WRITE_MULTIPLE and answer[:5] == request[:5]:
        words = [int.from_bytes(request[i:i + 2], "big") for i in range(6, len(request) - 1, 2)]
    out: dict[str, Any] = {}
    for address, raw in enumerate(words, start):
        reg = REGISTERS_BY_ADDRESS.get(address)
        if reg is not None and reg.writable and reg.name in SETTING_REGISTERS:
            out[SETTING_REGISTERS[reg.name]] = decode_value(reg, raw)
    return out


@functools.lru_cache(maxsize=1024)
def is_readable_span(start: int, count: int) -> bool:
    """Whether a read covers only registers the sensor has, floats not cut in half."""
    covered: set[int] = set()
    for reg in READABLE:
        covered.update(range(reg.address, reg.address + reg.count))
    if not all(a in covered for a in range(start, start + count)):
        return False
    first, last = REGISTERS_BY_ADDRESS.get(start), None
    for reg in READABLE:
        if reg.address <= start + count - 1 < reg.address + reg.count:
            last = reg
    # The read must start at a register's first word and end at one's last word.
    return first is not None and last is not None and last.address + last.count == start + count


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class ReadRequest:
    unit: int
    address: int
    count: int
    function: int = READ_HOLDING


@dataclass(frozen=True, slots=True)
class ReadResponse:
    unit: int
    registers: tuple[int, ...]
    function: int = READ_HOLDING


@dataclass(frozen=True, slots=True)
class WriteRegister:
    """FC06: the request and its echo have the same shape."""

    unit: int
    address: int
    value: int


@dataclass(frozen=True, slots=True)
class WriteRegisters:
    """FC16 request."""

    unit: int
    address: int
    values: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class WriteRegistersResponse:
    unit: int
    address: int
    count: int


@dataclass(frozen=True, slots=True)
class ExceptionAnswer:
    unit: int
    function: int
    code: int


RtuMessage = ReadRequest | ReadResponse | WriteRegister | WriteRegisters | \
    WriteRegistersResponse | ExceptionAnswer

_READ_REQUEST = {READ_HOLDING: ReadHoldingRegistersRequest, READ_INPUT: ReadInputRegistersRequest}
_READ_RESPONSE = {
    READ_HOLDING: ReadHoldingRegistersResponse, READ_INPUT: ReadInputRegistersResponse,
}


def _to_pdu(message: RtuMessage) -> ModbusPDU:
    match message:
        case ReadRequest(unit, address, count, function):
            if not 1 <= count <= MAX_READ:
                raise UsageError(f"read count {count} is not 1-{MAX_READ}")
            return _READ_REQUEST[function](dev_id=unit, address=address, count=count)
        case ReadResponse(unit, registers, function):
            return _READ_RESPONSE[function](dev_id=unit, registers=list(registers))
        case WriteRegister(unit, address, value):
            return WriteSingleRegisterRequest(dev_id=unit, address=address, registers=[value])
        case WriteRegisters(unit, address, values):
            if not 1 <= len(values) <= MAX_WRITE:
                raise UsageError(f"write count {len(values)} is not 1-{MAX_WRITE}")
            return WriteMultipleRegistersRequest(dev_id=unit, address=address,
                                                 registers=list(values))
        case WriteRegistersResponse(unit, address, count):
            return WriteMultipleRegistersResponse(dev_id=unit, address=address, count=count)
        case ExceptionAnswer(unit, function, code):
            pdu = PduException(function, code)
            pdu.dev_id = unit
            return pdu
    raise UsageError(f"not an RTU message: {message!r}")  # pragma: no cover


def _from_pdu(unit: int, pdu: ModbusPDU) -> RtuMessage:
    """The one place pymodbus PDU objects become our frozen messages."""
    function = pdu.function_code & 0x7F
    if isinstance(pdu, PduException):
        return ExceptionAnswer(unit, function, pdu.exception_code)
    if isinstance(pdu, ReadHoldingRegistersRequest):  # FC03 and FC04 requests
        return ReadRequest(unit, pdu.address, pdu.count, function)
    if isinstance(pdu, ReadHoldingRegistersResponse):
        return ReadResponse(unit, tuple(pdu.registers), function)
    if isinstance(pdu, WriteSingleRegisterResponse):  # request and echo alike
        return WriteRegister(unit, pdu.address, pdu.registers[0])
    if isinstance(pdu, WriteMultipleRegistersRequest):
        return WriteRegisters(unit, pdu.address, tuple(pdu.registers))
    if isinstance(pdu, WriteMultipleRegistersResponse):
        return WriteRegistersResponse(unit, pdu.address, pdu.count)
    raise UnknownFrame(f"function code {pdu.function_code} is not one the sensors use")


_BUILDER = FramerRTU(DecodePDU(is_server=False))


def encode(message: RtuMessage) -> bytes:
    """One RTU frame (address, PDU, CRC) for ``message``."""
    if not 0 <= message.unit <= 0xFF:
        raise UsageError(f"unit {message.unit} is not 0-255")
    try:
        return _BUILDER.buildFrame(_to_pdu(message))
    except (ValueError, struct.error, ModbusException) as exc:
        raise UsageError(f"cannot encode {message}: {exc}") from None


def encode_pdu(unit: int, pdu: bytes) -> bytes:
    """An RTU frame around a PDU given as bytes (Modbus TCP pass-through)."""
    if not 0 <= unit <= 0xFF:
        raise UsageError(f"unit {unit} is not 0-255")
    return _BUILDER.encode(pdu, unit, 0)


def read_request(unit: int, address: int, count: int, function: int = READ_HOLDING) -> bytes:
    return encode(ReadRequest(unit, address, count, function))


def write_request(unit: int, name: str, value: Any) -> bytes:
    """FC06 to the sensor's named writable register, the value converted by its kind."""
    register = WRITABLE.get(name)
    if register is None:
        raise UsageError(f"no writable sensor register {name!r}")
    return encode(WriteRegister(unit, register.address, encode_value(register, value)))


# --------------------------------------------------------------------------- framer


#: A read answer's registers (big-endian words), by their count.
_WORDS = tuple(struct.Struct(f">{count}H") for count in range(MAX_READ + 1))


@dataclass(slots=True)
class FramerStats:
    frames: int = 0
    garbage_bytes: int = 0
    bad_crcs: int = 0


class RtuFramer:
    """Finds RTU frames of the function codes the sensors use in a byte stream.

    ``requests=True`` reads what a master sends (the simulator's side); ``False`` reads
    answers (the gateway's side).  The two must be told apart because an RTU frame has
    no length field: FC03's request is 8 bytes, its answer 5 + 2n, decided by direction.

    Like ``NativeFramer`` it never throws away a byte that could start a frame, holds at
    most one partial candidate, and leaves giving up on a stalled candidate (the 3.5
    character silence of RTU) to the caller's ``expire()``.
    """

    MAX_FRAME = 256

    def __init__(self, *, requests: bool, any_unit: bool = False) -> None:
        """``any_unit``: take frames of units 0 and 248-255 too.  On a live line those
        are noise far more often than frames (no sensor may sit there); in a capture
        handed to ``decode_frame`` they are what the person wants read."""
        self.requests = requests
        self.any_unit = any_unit
        self._decoder = DecodePDU(is_server=requests)
        self._buf = bytearray()
        self.stats = FramerStats()

    @property
    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes) -> list[RtuMessage]:
        self._buf += data
        found: list[RtuMessage] = []
        while len(self._buf) >= 2:
            size = self._candidate_size()
            if size < 0:
                self._skip(1)
                continue
            if size == 0 or len(self._buf) < size:
                break  # plausible so far: wait for more bytes
            frame = bytes(self._buf[:size])
            if not FramerRTU.check_CRC(frame[:-2], int.from_bytes(frame[-2:], "big")):
                self.stats.bad_crcs += 1
                self._skip(1)
                continue
            message = self._message(frame)
            if message is None:
                self._skip(1)
                continue
            found.append(message)
            del self._buf[:size]
        self.stats.frames += len(found)
        return found

    def expire(self) -> list[RtuMessage]:
        if not self._buf:
            return []
        self._skip(1)
        return self.feed(b"")

    def _message(self, frame: bytes) -> RtuMessage | None:
        """A CRC-valid frame of a plausible size as a message (None: its content is
        refused).  A read answer, the frame of every poll, is read here: pymodbus's
        decoder costs five times as much for it (it formats the answer for a debug log
        that is off; docs/protocol-notes.md has the figures).  Everything else is
        pymodbus's to decode; content it would refuse (and log a warning about) is
        refused before."""
        function = frame[1]
        if not self.requests and function in (READ_HOLDING, READ_INPUT):
            # (size and even byte count are checked: 5 + byte count, as pymodbus says)
            return ReadResponse(frame[0], _WORDS[frame[2] // 2].unpack(frame[3:-2]),
                                function)
        pdu = self._decoder.decode(frame[1:-2]) if content_problem(frame) is None else None
        return None if pdu is None else _from_pdu(frame[0], pdu)

    def _candidate_size(self) -> int:
        """The frame size a candidate at the buffer's start would have: -1 implausible,
        0 not known yet."""
        buf = self._buf
        unit, function = buf[0], buf[1]
        if not self.any_unit and (unit > 247 or (unit == 0 and not self.requests)):
            return -1
        if function & 0x80:
            if self.requests or function & 0x7F not in FUNCTIONS:
                return -1
            if len(buf) >= 3 and not 1 <= buf[2] <= 0x0B:
                return -1
            return 5
        if function not in FUNCTIONS:
            return -1
        pdu_class = self._decoder.lookupPduClass(bytes(buf[:2]))
        if pdu_class is None:
            return -1
        size = int(pdu_class.calculateRtuFrameSize(bytes(buf)))
        if size and pdu_class.rtu_byte_count_pos:
            byte_count = buf[pdu_class.rtu_byte_count_pos]
            if byte_count % 2 or byte_count == 0 or size > self.MAX_FRAME:
                return -1
        return size

    def _skip(self, count: int) -> None:
        self.stats.garbage_bytes += count
        del self._buf[:count]


def content_problem(frame: bytes) -> str | None:
    """What is wrong with a CRC-valid frame's content, in words, or None.  Only the
    counts pymodbus checks when decoding need checking: they are in the request."""
    function = frame[1]
    if function in (READ_HOLDING, READ_INPUT) and len(frame) == 8:
        count = int.from_bytes(frame[4:6], "big")
        if not 1 <= count <= MAX_READ:
            return f"read count {count} is not 1-{MAX_READ}"
    if function == WRITE_MULTIPLE and len(frame) > 8:
        count, byte_count = int.from_bytes(frame[4:6], "big"), frame[6]
        if not 1 <= count <= MAX_WRITE or byte_count != 2 * count:
            return f"write of {count} registers with {byte_count} data bytes"
    return None


def decode_frame(raw: bytes) -> RtuMessage:
    """One whole captured frame, request or answer, to a message.

    Tried as an answer first, then as a request; it must be exactly one frame.  Any
    unit 0-255 is read: a frame whose CRC holds is what was on the wire, broadcast or
    reserved address alike.  A frame whose CRC fails is said to be cut short (or to
    carry bytes after a whole frame) when its header says so, rather than blamed on
    its CRC.
    """
    if len(raw) < 4 or FramerRTU.compute_CRC(raw[:-2]) != int.from_bytes(raw[-2:], "big"):
        raise _why_not_whole(raw)
    for requests in (False, True):
        framer = RtuFramer(requests=requests, any_unit=True)
        messages = framer.feed(raw)
        if len(messages) == 1 and framer.stats.garbage_bytes == 0 and framer.pending == 0:
            return messages[0]
    if raw[1] & 0x7F not in FUNCTIONS:
        raise UnknownFrame(f"function code {raw[1]:02X} is not one the sensors use")
    byte_count = raw[2] if len(raw) > 2 else 0
    if raw[1] in (READ_HOLDING, READ_INPUT) and byte_count and byte_count % 2 == 0:
        raise BadLength(f"an FC{raw[1]:02d} answer of {byte_count} data bytes is "
                        f"{byte_count + 5} bytes, not {len(raw)}")
    if (problem := content_problem(raw)) is not None:
        raise FrameError(problem)
    raise BadLength(f"{len(raw)} bytes are not one whole FC{raw[1] & 0x7F:02d} frame")


def frame_sizes(raw: bytes) -> list[int]:
    """The sizes an RTU frame starting with ``raw`` would have: as an answer, then as
    a request (pymodbus's size of each function code), each only where the bytes so far
    make sense for it (a byte count that is even, a register count of 1-125).  Empty
    when the header is unknown or too short to tell."""
    if len(raw) < 2:
        return []
    function = raw[1]
    if function & 0x80:
        return [5] if function & 0x7F in FUNCTIONS else []
    if function not in FUNCTIONS:
        return []
    sizes: list[int] = []
    for requests in (False, True):
        pdu_class = DecodePDU(is_server=requests).lookupPduClass(bytes(raw[:2]))
        size = int(pdu_class.calculateRtuFrameSize(raw)) if pdu_class is not None else 0
        if size and _plausible_start(raw, requests) and size not in sizes:
            sizes.append(size)
    return sizes


def _plausible_start(raw: bytes, request: bool) -> bool:
    """Whether the first bytes of ``raw`` can begin a frame of its function code in
    that direction: a read answer's byte count is even and not zero, a request's
    register count is one a device accepts."""
    function = raw[1]
    if not request:
        return function not in (READ_HOLDING, READ_INPUT) or (raw[2] > 0 and raw[2] % 2 == 0)
    if function in (READ_HOLDING, READ_INPUT, WRITE_MULTIPLE) and len(raw) >= 6:
        count = int.from_bytes(raw[4:6], "big")
        limit = MAX_WRITE if function == WRITE_MULTIPLE else MAX_READ
        return 1 <= count <= limit and (function != WRITE_MULTIPLE or len(raw) < 7
                                        or raw[6] == 2 * count)
    return True


def _why_not_whole(raw: bytes) -> FrameError:
    """The likeliest reason ``raw``, whose CRC fails (or which is too short to have
    one), is not a frame: cut short, a whole frame with bytes after it, or a bad CRC."""
    sizes = frame_sizes(raw)
    if len(raw) not in sizes and (longer := [n for n in sizes if n > len(raw)]):
        return BadLength(f"truncated: {len(raw)} of {longer[0]} bytes "
                         f"(an FC{raw[1] & 0x7F:02d} frame)")
    for size in (n for n in sizes if 4 <= n < len(raw)):
        if FramerRTU.check_CRC(raw[:size - 2], int.from_bytes(raw[size - 2:size], "big")):
            extra = len(raw) - size
            return BadLength(f"a whole {size}-byte FC{raw[1] & 0x7F:02d} frame, then "
                             f"{extra} more byte{'s' if extra > 1 else ''}")
    if len(raw) < 4:
        return BadLength(f"an RTU frame is at least 4 bytes, got {len(raw)}")
    crc = FramerRTU.compute_CRC(raw[:-2])
    return BadChecksum(f"CRC {raw[-2:].hex().upper()}, expected {crc:04X}")


def describe(message: RtuMessage, start: int | None = None) -> dict[str, Any]:
    """A message as plain fields, with register names and values where known.

    ``start`` is the first register of the read a ``ReadResponse`` answers.
    """
    out: dict[str, Any] = {"unit": message.unit}
    match message:
        case ReadRequest(_, address, count, function):
            out |= {"frame": "read_request", "function": function, "start": address,
                    "count": count}
        case ReadResponse(_, registers, function):
            out |= {"frame": "read_response", "function": function,
                    "registers": list(registers)}
            if start is not None:
                out["start"] = start
                out["values"] = read_values(start, registers)
        case WriteRegister(_, address, value):
            reg = REGISTERS_BY_ADDRESS.get(address)
            out |= {"frame": "write", "address": address, "raw": value}
            if reg is not None and reg.writable:
                out["register"] = reg.name
                out["value"] = decode_value(reg, value)
        case WriteRegisters(_, address, values):
            out |= {"frame": "write_multiple", "address": address, "values": list(values)}
        case WriteRegistersResponse(_, address, count):
            out |= {"frame": "write_multiple_response", "address": address, "count": count}
        case ExceptionAnswer(_, function, code):
            out |= {"frame": "exception", "function": function, "code": code}
    return out

