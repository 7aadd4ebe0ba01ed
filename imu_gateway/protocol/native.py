"""The sensors' native binary protocol (the vendor's native protocol document), sans-IO.

Frame::

    77 LEN ADDR CMD DATA... SUM

``LEN`` counts from itself to ``SUM`` inclusive, so a frame is ``LEN + 1`` bytes.
``SUM`` is the low byte of the sum of LEN, ADDR, CMD and DATA.

Why one table instead of a parser per command: the answer's command word follows no
single rule.  Angle reads answer ``0x80 | cmd``; the data reads 0x50/0x54/0x55/0x57
answer with the same word; 0x59 answers 0x59 (43 data bytes on VG/MINS, 52 on AH) but
an IMU answers 0x59 with **0x84** and 18 bytes (2.13); gyro calibration 0x52 answers
**0xA5**; 0x1F and 0x56 answer with their own word; 0x82 (clear heading) and 0x84
(relative heading) are echoed.  So 0x84 means "three angles" at LEN 0x0D, "IMU
gyro+accel" at LEN 0x16 and "relative heading ack" at LEN 0x07; 0x82 means "roll" at
LEN 0x07 and "clear heading ack" at LEN 0x04.  Every frame is therefore identified by
its (command word, LEN) pair, looked up in ``REQUEST_SHAPES`` or ``ANSWER_SHAPES``,
which are built from the command table ``COMMANDS`` below; an import-time check proves
the pairs unambiguous in each direction.  One pair means one thing as a request and
another as an answer: 2.16's ``77 05 .. 56 XX`` asks for output type XX, and the answer,
with the same word and length, carries a status byte (``TWO_WAY``).  Whoever knows
which side sent a frame says so (``interpret(..., direction=...)``).

Nothing here does I/O or reads a clock.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Protocol

from ..model import Series
from . import bcd
from .errors import BadChecksum, BadLength, FrameError, UnknownFrame, UsageError

SYNC = 0x77
#: Bytes before DATA (77 LEN ADDR CMD) and after it (SUM).
OVERHEAD = 5

ALL_SERIES = frozenset(Series)
AH_ONLY = frozenset({Series.AH})
MINS_ONLY = frozenset({Series.MINS})


def checksum(body: bytes | bytearray) -> int:
    """Low byte of the sum of LEN, ADDR, CMD and DATA (``body`` excludes 0x77 and SUM)."""
    return sum(body) & 0xFF


# --------------------------------------------------------------------------- fields


class Codec(Protocol):
    """How one field's bytes map to a Python value and back."""

    @property
    def size(self) -> int: ...

    def encode(self, value: Any) -> bytes: ...

    def decode(self, data: bytes) -> Any: ...


@dataclass(frozen=True, slots=True)
class Bcd:
    """A signed packed-BCD value (see ``bcd``)."""

    fmt: bcd.BcdFormat

    @property
    def size(self) -> int:
        return self.fmt.size

    def encode(self, value: float) -> bytes:
        return self.fmt.encode(value)

    def decode(self, data: bytes) -> float:
        return self.fmt.decode(data)


@dataclass(frozen=True, slots=True)
class Byte:
    """One unsigned byte taken as it is (addresses, undocumented result codes)."""

    size = 1

    def encode(self, value: int) -> bytes:
        if not isinstance(value, int) or not 0 <= value <= 0xFF:
            raise UsageError(f"{value!r} is not a byte (0-255)")
        return bytes([value])

    def decode(self, data: bytes) -> int:
        return data[0]


@dataclass(frozen=True, slots=True, eq=False)  # codecs are singletons: identity will do
class Choice:
    """A byte code with a documented meaning per value.

    ``aliases`` are extra codes accepted when decoding only.  With ``raw_others`` a code
    the document does not name decodes to the plain integer instead of being an error,
    and a plain integer encodes as itself.  ``unnamed_decodes`` does the decoding half
    only: for codes whose meanings are numbers themselves (a baud rate), where encoding
    a bare integer could not tell a code from a meaning.
    """

    meanings: Mapping[int, Any]
    aliases: Mapping[int, Any] = field(default_factory=dict)
    raw_others: bool = False
    unnamed_decodes: bool = False

    size = 1

    def encode(self, value: Any) -> bytes:
        for code, meaning in self.meanings.items():
            if meaning == value:
                return bytes([code])
        if self.raw_others and isinstance(value, int) and 0 <= value <= 0xFF:
            return bytes([value])
        raise UsageError(f"{value!r} is not one of {sorted(map(str, self.meanings.values()))}")

    def decode(self, data: bytes) -> Any:
        code = data[0]
        if code in self.meanings:
            return self.meanings[code]
        if code in self.aliases:
            return self.aliases[code]
        if self.raw_others or self.unnamed_decodes:
            return code
        raise FrameError(f"code 0x{code:02X} is not one of {sorted(self.meanings)}")


#: 2.4: the baud-rate codes (the Modbus document uses the same codes).
BAUD_CODES: Mapping[int, int] = MappingProxyType(
    {0: 2400, 1: 4800, 2: 9600, 3: 19200, 4: 115200, 5: 38400, 6: 57600, 7: 460800}
)
#: 2.17: auto-output rate codes; 0 is answer (polled) mode.
OUTPUT_RATE_CODES: Mapping[int, int] = MappingProxyType(
    {0: 0, 1: 5, 2: 10, 3: 20, 4: 25, 5: 50, 6: 100, 7: 200, 8: 500}
)

ANGLE = Bcd(bcd.ANGLE)
ACCEL = Bcd(bcd.ACCEL)
RATE = Bcd(bcd.RATE)
MAG = Bcd(bcd.MAG)
QUAT = Bcd(bcd.QUATERNION)
DECL = Bcd(bcd.DECLINATION)
# 2.4: a code the table does not name must still be read, so that a sensor can answer
# it with 0xFF (failure); it decodes to its number, which no baud rate (>= 2400) is.
BAUD = Choice(BAUD_CODES, unnamed_decodes=True)
OUTPUT_RATE = Choice(OUTPUT_RATE_CODES)
# 2.4, 2.5, 2.7: 0x00 success, 0xFF failure.  Answers whose byte the document shows
# only as 0x00 (2.8, 2.16, 2.17, 2.24-2.26) use the same codec.  A code no document names is
# passed on as its number rather than guessed to be a failure (2.18 answers 0x01 for
# success, so a sensor might well echo other codes).
RESULT = Choice({0x00: "success", 0xFF: "failure"}, raw_others=True)
# 2.8 sets 0x01 for relative, but 2.9 answers 0xFF for relative: accept both on decode.
ZERO_TYPE_SET = Choice({0x00: "absolute", 0x01: "relative"})
ZERO_TYPE_QUERY = Choice({0x00: "absolute", 0xFF: "relative"}, aliases={0x01: "relative"})


@dataclass(frozen=True, slots=True)
class Field:
    name: str
    codec: Codec


def _fields(*pairs: tuple[str, Codec]) -> tuple[Field, ...]:
    return tuple(Field(name, codec) for name, codec in pairs)


def _triple(prefix: str, codec: Codec) -> tuple[Field, ...]:
    return _fields((f"{prefix}_x", codec), (f"{prefix}_y", codec), (f"{prefix}_z", codec))


# Field names are the reading JSON's per-field names (``pitch``, ``accel_x``, ``q0`` …)
# so that normalising is a lookup.
ANGLES3 = _fields(("pitch", ANGLE), ("roll", ANGLE), ("yaw", ANGLE))
ACCEL3 = _triple("accel", ACCEL)
GYRO3 = _triple("gyro", RATE)
MAG3 = _triple("mag", MAG)
QUAT4 = _fields(("q0", QUAT), ("q1", QUAT), ("q2", QUAT), ("q3", QUAT))


# --------------------------------------------------------------------------- shapes


class Direction(enum.Flag):
    REQUEST = enum.auto()
    ANSWER = enum.auto()
    ECHO = REQUEST | ANSWER  # the answer repeats the request byte for byte in shape


@dataclass(frozen=True, slots=True)
class Shape:
    """One frame layout: a command word, a data layout, who sends it and which series."""

    name: str
    command: int
    fields: tuple[Field, ...]
    direction: Direction
    series: frozenset[Series]
    section: str
    # Worked out from the fields once (an answer is read hundreds of times a second):
    data_size: int = field(init=False, repr=False, compare=False)
    #: The LEN byte: LEN, ADDR, CMD, DATA and SUM.
    length_byte: int = field(init=False, repr=False, compare=False)
    #: (command word, LEN byte): what tells this frame from every other.
    key: tuple[int, int] = field(init=False, repr=False, compare=False)
    #: Each field's name, where its bytes lie in DATA and the decoder they go through.
    layout: tuple[tuple[str, int, int, Callable[[bytes], Any]], ...] = field(
        init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        layout, offset = [], 0
        for f in self.fields:
            layout.append((f.name, offset, offset + f.codec.size, f.codec.decode))
            offset += f.codec.size
        object.__setattr__(self, "data_size", offset)
        object.__setattr__(self, "length_byte", offset + 4)
        object.__setattr__(self, "key", (self.command, offset + 4))
        object.__setattr__(self, "layout", tuple(layout))


@dataclass(frozen=True, slots=True)
class NativeCommand:
    """A request and the answer each series gives to it (``None``: no answer)."""

    name: str
    section: str
    request: Shape
    answers: Mapping[Series, Shape]
    #: 2.5: the sensor answers from the address it was just given.
    answers_from_new_address: bool = False
    #: 2.6: the address query is always sent to 00 and any sensor answers it.
    any_address: bool = False

    def answer_for(self, series: Series) -> Shape | None:
        return self.answers.get(series)


def _command(
    name: str,
    section: str,
    series: frozenset[Series],
    request: tuple[int, tuple[Field, ...]],
    answer: tuple[int, tuple[Field, ...]] | None,
    *,
    echo: bool = False,
    per_series: Mapping[Series, tuple[int, tuple[Field, ...]]] | None = None,
    **flags: bool,
) -> NativeCommand:
    req_word, req_fields = request
    req_shape = Shape(
        name,
        req_word,
        req_fields,
        Direction.ECHO if echo else Direction.REQUEST,
        series,
        section,
    )
    if echo:
        return NativeCommand(
            name, section, req_shape, MappingProxyType(dict.fromkeys(series, req_shape)), **flags
        )
    # Series that give the same answer share one shape naming all of them (VG and MINS
    # give the same 0x59 answer; IMU and AH each have their own).
    senders: dict[tuple[int, tuple[str, ...]], tuple[tuple[Field, ...], set[Series]]] = {}
    for s in series:
        spec = (per_series or {}).get(s, answer)
        if spec is not None:
            word, fields_ = spec
            senders.setdefault((word, tuple(f.name for f in fields_)), (fields_, set()))[1].add(s)
    answers = {
        s: shape
        for (word, _), (fields_, members) in senders.items()
        for shape in [Shape(name, word, fields_, Direction.ANSWER, frozenset(members), section)]
        for s in members
    }
    return NativeCommand(name, section, req_shape, MappingProxyType(answers), **flags)


NO_DATA: tuple[Field, ...] = ()
ADDRESS = _fields(("address", Byte()))

# Every command of sections 2.1-2.26, in document order.  The request word and data,
# then the answer word and data; see the module docstring for the quirks this encodes.
#
# 2.1-2.3 and 2.12 name no series (2.13-2.15 and 2.19-2.26 do), so every series may
# send them, an IMU included; which command a series is *polled* with is the bus's
# choice (``exchanges``), not a limit of the protocol.
COMMANDS: tuple[NativeCommand, ...] = (
    _command("read_pitch", "2.1", ALL_SERIES,
             (0x01, NO_DATA), (0x81, _fields(("pitch", ANGLE)))),
    _command("read_roll", "2.2", ALL_SERIES,
             (0x02, NO_DATA), (0x82, _fields(("roll", ANGLE)))),
    _command("read_angles", "2.3", ALL_SERIES, (0x04, NO_DATA), (0x84, ANGLES3)),
    _command("set_baudrate", "2.4", ALL_SERIES,
             (0x0B, _fields(("baudrate", BAUD))), (0x8B, _fields(("result", RESULT)))),
    _command("set_address", "2.5", ALL_SERIES,
             (0x0F, _fields(("new_address", Byte()))), (0x8F, _fields(("result", RESULT))),
             answers_from_new_address=True),
    _command("read_address", "2.6", ALL_SERIES,
             (0x1F, NO_DATA), (0x1F, ADDRESS), any_address=True),
    _command("save", "2.7", ALL_SERIES, (0x0A, NO_DATA), (0x8A, _fields(("result", RESULT)))),
    _command("set_zero_type", "2.8", ALL_SERIES,
             (0x05, _fields(("zero_type", ZERO_TYPE_SET))), (0x85, _fields(("result", RESULT)))),
    _command("read_zero_type", "2.9", ALL_SERIES,
             (0x0D, NO_DATA), (0x8D, _fields(("zero_type", ZERO_TYPE_QUERY)))),
    _command("read_accel", "2.10", ALL_SERIES, (0x54, NO_DATA), (0x54, ACCEL3)),
    _command("read_gyro", "2.11", ALL_SERIES, (0x50, NO_DATA), (0x50, GYRO3)),
    _command("read_quaternion", "2.12", ALL_SERIES, (0x57, NO_DATA), (0x57, QUAT4)),
    # 2.13-2.15: one request, three answers.
    _command("read_all", "2.13-2.15", ALL_SERIES, (0x59, NO_DATA), None,
             per_series={
                 Series.IMU: (0x84, GYRO3 + ACCEL3),
                 Series.VG: (0x59, ANGLES3 + ACCEL3 + GYRO3 + QUAT4),
                 Series.MINS: (0x59, ANGLES3 + ACCEL3 + GYRO3 + QUAT4),
                 Series.AH: (0x59, ANGLES3 + ACCEL3 + GYRO3 + MAG3 + QUAT4),
             }),
    # 2.16 answers 0x56 with one byte the document prints as 00 whatever type was asked
    # (as 2.17 does): a status, not an echo of the type.  RESULT reads FF as failure and
    # any other code as not one, so a sensor that does echo the type is understood too.
    _command("set_output_type", "2.16", ALL_SERIES,
             (0x56, _fields(("output_type", Byte()))), (0x56, _fields(("result", RESULT)))),
    _command("set_output_rate", "2.17", ALL_SERIES,
             (0x0C, _fields(("rate_hz", OUTPUT_RATE))), (0x8C, _fields(("result", RESULT)))),
    _command("calibrate_gyro", "2.18", ALL_SERIES,
             (0x52, NO_DATA), (0xA5, _fields(("code", Byte())))),
    _command("clear_heading", "2.19", MINS_ONLY, (0x82, NO_DATA), None, echo=True),
    _command("set_relative_heading", "2.20", MINS_ONLY,
             (0x84, _fields(("degrees", ANGLE))), None, echo=True),
    # 2.21's answer data is garbled in the document ("X n 00 in"); its LEN 0x06 gives two
    # bytes, which we read as the declination echoed in the request's format.
    _command("set_declination", "2.21", AH_ONLY,
             (0x06, _fields(("degrees", DECL))), (0x86, _fields(("degrees", DECL)))),
    _command("read_declination", "2.22", AH_ONLY,
             # "declination", not "degrees": read_settings answers with it, and the settings
             # everywhere else (KnownSettings, the settings topic) call it so
             (0x07, NO_DATA), (0x87, _fields(("declination", DECL)))),
    _command("read_mag", "2.23", AH_ONLY, (0x55, NO_DATA), (0x55, MAG3)),
    _command("clear_mag_calibration", "2.24", AH_ONLY,
             (0x10, NO_DATA), (0x90, _fields(("result", RESULT)))),
    _command("start_mag_calibration", "2.25", AH_ONLY,
             (0x11, NO_DATA), (0x91, _fields(("result", RESULT)))),
    _command("finish_mag_calibration", "2.26", AH_ONLY,
             (0x12, NO_DATA), (0x92, _fields(("result", RESULT)))),
)

COMMANDS_BY_NAME: Mapping[str, NativeCommand] = MappingProxyType({c.name: c for c in COMMANDS})


def _index_shapes(commands: Iterable[NativeCommand],
                  direction: Direction) -> dict[tuple[int, int], Shape]:
    """(command word, LEN) -> the shape sent in ``direction``, refusing any pair that
    would mean two things there."""
    index: dict[tuple[int, int], Shape] = {}
    for command in commands:
        for shape in (command.request, *command.answers.values()):
            if not shape.direction & direction:
                continue
            seen = index.get(shape.key)
            if seen is None:
                index[shape.key] = shape
            elif seen != shape:
                raise AssertionError(f"ambiguous native frame {shape.key}: {seen} / {shape}")
    return index


#: What a sensor may hear, and what a master may hear (echo shapes are in both).
REQUEST_SHAPES: Mapping[tuple[int, int], Shape] = MappingProxyType(
    _index_shapes(COMMANDS, Direction.REQUEST))
ANSWER_SHAPES: Mapping[tuple[int, int], Shape] = MappingProxyType(
    _index_shapes(COMMANDS, Direction.ANSWER))
#: Pairs that are one frame as a request and another as an answer (2.16 only).
TWO_WAY: frozenset[tuple[int, int]] = frozenset(
    k for k in REQUEST_SHAPES.keys() & ANSWER_SHAPES.keys()
    if REQUEST_SHAPES[k] != ANSWER_SHAPES[k]
)
#: Every frame the documents describe, by (command word, LEN byte).  A ``TWO_WAY`` pair
#: reads as its request here: a frame of unknown origin is read as what a master sends,
#: and ``interpret`` is told the direction when it is known.
SHAPES: Mapping[tuple[int, int], Shape] = MappingProxyType(
    {**ANSWER_SHAPES, **REQUEST_SHAPES})
_LENGTHS = frozenset(length for _, length in SHAPES)
MAX_FRAME = max(_LENGTHS) + 1

#: 2.16: what each auto-output type code streams, per series, as the read command
#: whose answer frame is sent.  (IMU's code 2 is the 2.13 frame: read_all's IMU answer.)
_VG_OUTPUT = {0: "read_angles", 1: "read_accel", 2: "read_gyro", 3: "read_angles",
              4: "read_quaternion", 5: "read_all"}
OUTPUT_TYPES: Mapping[Series, Mapping[int, str]] = MappingProxyType({
    Series.VG: _VG_OUTPUT,
    Series.MINS: _VG_OUTPUT,
    Series.AH: {**_VG_OUTPUT, 3: "read_mag"},
    Series.IMU: {0: "read_gyro", 1: "read_accel", 2: "read_all"},
})


# --------------------------------------------------------------------------- frames


@dataclass(frozen=True, slots=True)
class NativeFrame:
    """A structurally valid frame: sync, length and checksum are right."""

    address: int
    command: int
    data: bytes

    def encode(self) -> bytes:
        body = bytes([len(self.data) + 4, self.address, self.command]) + self.data
        return bytes([SYNC]) + body + bytes([checksum(body)])


@dataclass(frozen=True, slots=True)
class NativeMessage:
    """A frame read through its shape: what it is and the values it carries."""

    shape: Shape
    address: int
    values: Mapping[str, Any]

    @property
    def name(self) -> str:
        return self.shape.name


def parse_frame(raw: bytes) -> NativeFrame:
    """Check one whole frame's sync, length and checksum."""
    if len(raw) < OVERHEAD:
        raise BadLength(f"a native frame is at least {OVERHEAD} bytes, got {len(raw)}")
    if raw[0] != SYNC:
        raise FrameError(f"a native frame starts with 77, not {raw[0]:02X}")
    if raw[1] + 1 > len(raw):
        raise BadLength(f"truncated: {len(raw)} of {raw[1] + 1} bytes (LEN byte {raw[1]:02X})")
    if raw[1] + 1 != len(raw):
        raise BadLength(f"LEN byte {raw[1]:02X} says {raw[1] + 1} bytes, got {len(raw)}")
    if checksum(raw[1:-1]) != raw[-1]:
        raise BadChecksum(f"checksum {raw[-1]:02X}, expected {checksum(raw[1:-1]):02X}")
    return NativeFrame(raw[2], raw[3], bytes(raw[4:-1]))


_SHAPES_OF: Mapping[Direction | None, Mapping[tuple[int, int], Shape]] = MappingProxyType({
    None: SHAPES, Direction.REQUEST: REQUEST_SHAPES, Direction.ANSWER: ANSWER_SHAPES,
})


def interpret(frame: NativeFrame, series: Series | None = None,
              direction: Direction | None = None) -> NativeMessage:
    """Read a frame through the shape its (command, LEN) names.

    With ``series`` given, a shape that series never sends or accepts is refused.
    ``direction`` (``REQUEST``: a master sent it, ``ANSWER``: a sensor did) matters for
    the ``TWO_WAY`` pairs only; without it they read as requests.
    """
    shape = _SHAPES_OF[direction].get((frame.command, len(frame.data) + 4))
    if shape is None:
        raise UnknownFrame(
            f"no documented frame has command {frame.command:02X} "
            f"with {len(frame.data)} data bytes"
        )
    if series is not None and series not in shape.series:
        allowed = "/".join(sorted(s.name for s in shape.series))
        raise UnknownFrame(
            f"this {shape.name} frame ({shape.section}) comes from {allowed}, not {series.name}"
        )
    values: dict[str, Any] = {}
    data = frame.data
    for name, start, stop, decode_field in shape.layout:
        try:
            values[name] = decode_field(data[start:stop])
        except FrameError as exc:
            raise type(exc)(f"{shape.name} field {name}: {exc}") from None
    return NativeMessage(shape, frame.address, MappingProxyType(values))


def decode(raw: bytes, series: Series | None = None,
           direction: Direction | None = None) -> NativeMessage:
    """``parse_frame`` then ``interpret``: one whole frame to a message."""
    return interpret(parse_frame(raw), series, direction)


def encode(shape: Shape, address: int, /, **values: Any) -> bytes:
    """Build a frame of ``shape`` carrying ``values`` (one per field, by name).

    ``address`` is positional-only because 2.6's answer has a field named address.
    """
    missing = [f.name for f in shape.fields if f.name not in values]
    extra = sorted(set(values) - {f.name for f in shape.fields})
    if missing or extra:
        raise UsageError(f"{shape.name}: missing {missing}, unexpected {extra}")
    if not 0 <= address <= 0xFF:
        raise UsageError(f"address {address} is not 0-255")
    data = b"".join(f.codec.encode(values[f.name]) for f in shape.fields)
    return NativeFrame(address, shape.command, data).encode()


def encode_request(name: str, address: int = 0, /, **values: Any) -> bytes:
    """The request frame of command ``name`` (a key of ``COMMANDS_BY_NAME``)."""
    try:
        command = COMMANDS_BY_NAME[name]
    except KeyError:
        raise UsageError(f"no native command {name!r}") from None
    return encode(command.request, 0 if command.any_address else address, **values)


def encode_answer(name: str, series: Series, address: int, /, **values: Any) -> bytes:
    """The answer a ``series`` sensor gives to command ``name``."""
    command = COMMANDS_BY_NAME.get(name)
    if command is None:
        raise UsageError(f"no native command {name!r}")
    shape = command.answer_for(series)
    if shape is None:
        raise UsageError(f"{series.name} sends no answer to {name}")
    return encode(shape, address, **values)


# --------------------------------------------------------------------------- framer


@dataclass(slots=True)
class FramerStats:
    frames: int = 0
    garbage_bytes: int = 0
    bad_checksums: int = 0


class NativeFramer:
    """Turns a byte stream, in any chunking, into checksum-valid frames.

    A candidate frame starts at 0x77 and must have a (command, LEN) pair of the shapes
    it is given; that check rejects most noise after two to four bytes.  A stray prefix
    that happens to be a known pair (``77 38 00 59``) still makes it wait for the rest:
    the caller ends that with ``expire()`` when the line goes quiet.  A sensor's framer
    knows only request shapes (at most 8 bytes), a master's only answers, which
    narrows the pairs noise can hit.

    On a bad checksum only the candidate's 0x77 is dropped and the search goes on from
    the next byte, because a real frame may start inside the rejected one
    (0x77 is a valid BCD byte: 077.xx degrees).  The buffer never holds more than one
    candidate, so it is bounded by ``MAX_FRAME``.

    A partial candidate that never completes (the line went quiet) is the caller's to
    give up on with ``expire()``: only the caller knows the time.
    """

    def __init__(self, shapes: Mapping[tuple[int, int], Shape] = SHAPES) -> None:
        self._known = frozenset(shapes)
        self._lengths = frozenset(length for _, length in shapes)
        self._buf = bytearray()
        self.stats = FramerStats()

    @property
    def pending(self) -> int:
        """Bytes held back as the start of a frame not yet complete."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[NativeFrame]:
        self._buf += data
        frames: list[NativeFrame] = []
        buf = self._buf
        while buf:
            start = buf.find(SYNC)
            if start < 0:
                self._skip(len(buf))
                break
            self._skip(start)
            if len(buf) >= 2 and buf[1] not in self._lengths:
                self._skip(1)
                continue
            if len(buf) < 4:
                break
            if (buf[3], buf[1]) not in self._known:
                self._skip(1)
                continue
            total = buf[1] + 1
            if len(buf) < total:
                break
            if checksum(buf[1 : total - 1]) != buf[total - 1]:
                self.stats.bad_checksums += 1
                self._skip(1)
                continue
            frames.append(NativeFrame(buf[2], buf[3], bytes(buf[4 : total - 1])))
            del buf[:total]
        self.stats.frames += len(frames)
        return frames

    def expire(self) -> list[NativeFrame]:
        """Give up on the partial candidate at the front and look behind it."""
        if not self._buf:
            return []
        self._skip(1)
        return self.feed(b"")

    def _skip(self, count: int) -> None:
        self.stats.garbage_bytes += count
        del self._buf[:count]
