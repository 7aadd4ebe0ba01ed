"""Request/answer pairing for the bus master, sans-IO.

An ``Exchange`` is one request on the wire and the rule that recognises its answer
among whatever frames arrive.  A command is a short list of exchanges; each may carry
an ``Effect`` the bus master must apply once it succeeds (follow a new baud rate, use
a new address, keep out of a sensor's way while it saves).  The protocol quirks that
decide those effects live here, next to the frames, not in the bus master:

* native baud change: answered at the old rate, then the line must switch (2.4);
* Modbus baud change: never answered, effective at once (2.3): switch, then verify;
* address change: answered from the *new* address, in both protocols;
* save: 3-5 s during which the sensor does not answer; we keep away for 5 s;
* Modbus gyro calibration: "started" (0) now and an unsolicited "done" later, or
  "complete" (1) at once.  While it runs the sensor is busy for commands but still
  read: nothing in the document says it stops answering (docs/protocol-notes.md).

``ProtocolAdapter`` gives the bus master one face for both protocols: its framer,
the poll of a series, the exchanges of a command, the auto-output set-up, and the
reading of unsolicited (streamed) frames.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Protocol

from ..modbus_codes import READ_HOLDING, READ_INPUT, WRITE_MULTIPLE, WRITE_SINGLE
from ..model import Series
from ..model import WireProtocol as Wire
from . import modbus_rtu as rtu
from . import native
from .errors import FrameError, UsageError

#: Save lasts 3-5 s (native 2.7); we wait for the upper bound before talking again.
SAVE_SECONDS = 5.0
#: How long a Modbus gyro calibration may take before we stop waiting for "done".
GYRO_CAL_SECONDS = 10.0


#: A whole frame as a framer hands it to the bus: a native frame, or a Modbus RTU
#: message.  What crosses from the protocol to the bus is one of these, never ``Any``.
Frame = native.NativeFrame | rtu.RtuMessage


def sender(frame: Frame) -> int:
    """The address a frame came from (a native address, a Modbus unit)."""
    return frame.address if isinstance(frame, native.NativeFrame) else frame.unit


def char_time(baud: int) -> float:
    """Seconds per character at 8N1 (start bit, 8 data bits, stop bit)."""
    return 10 / baud


def rtu_silence(baud: int) -> float:
    """The 3.5-character gap Modbus RTU requires before a frame (1.75 ms above 19200)."""
    return 3.5 * char_time(baud) if baud <= 19200 else 0.00175


@dataclass(frozen=True, slots=True)
class Effect:
    """What the bus master must do once an exchange succeeded."""

    new_baud: int | None = None  # switch the line to this rate
    new_address: int | None = None  # the sensor now answers here
    busy_for: float = 0.0  # keep the sensor out of the schedule this long
    busy_until_done: bool = False  # busy until an unsolicited "done" (Modbus gyro cal)
    #: while busy, keep polling: the busy period holds back commands only (a Modbus
    #: gyro calibration; a save's sensor is deaf, so a save never sets it)
    read_while_busy: bool = False


#: No effect at all: what an answer that says "already complete" asks for.
NO_EFFECT = Effect()


@dataclass(frozen=True, slots=True)
class Answer:
    """A recognised answer: its decoded values, and whether the sensor said "ok"."""

    values: Mapping[str, Any]
    ok: bool = True
    detail: str = ""
    #: what the answer itself calls for, in place of the exchange's own ``effect``
    #: (``None``: the exchange's).  A Modbus gyro calibration answered with 1 is
    #: complete already: ``NO_EFFECT``, no busy period.
    effect: Effect | None = None


#: An exchange's rule for recognising its answer: the frame's ``Answer``, or None.
Match = Callable[[Frame], Answer | None]


@dataclass(frozen=True, slots=True)
class Exchange:
    label: str
    request: bytes
    #: the answer's length in bytes (for the wire-time budget); 0: no answer comes
    answer_bytes: int
    #: frame -> its Answer when it answers this request, else None (someone else's)
    match: Match = field(repr=False)
    effect: Effect = Effect()


class Framer(Protocol):
    def feed(self, data: bytes) -> Sequence[Frame]: ...

    def expire(self) -> Sequence[Frame]: ...

    @property
    def pending(self) -> int: ...


class ProtocolAdapter(Protocol):
    """What the bus master needs to know about one protocol."""

    wire: Wire

    def new_framer(self) -> Framer: ...

    def garbage_seen(self, framer: Framer) -> int:
        """Skipped bytes plus bad checksums so far (to tell noise from silence)."""
        ...

    def gap_before_request(self, baud: int) -> float: ...

    def poll(self, series: Series, address: int) -> Exchange: ...

    def carries(self, name: str) -> bool:
        """Whether the protocol has a row for the catalogue command ``name``."""
        ...

    def command(self, series: Series, address: int, name: str,
                args: Mapping[str, Any]) -> list[Exchange]: ...

    def stream_start(self, series: Series, address: int, hz: float) -> list[Exchange]: ...

    def stream_stop(self, series: Series, address: int) -> list[Exchange]: ...

    def unsolicited(self, frame: Frame, series: Series, address: int) -> Answer | None:
        """A frame nobody asked for, if it is this sensor's data (auto-output) or its
        "done" (Modbus gyro calibration, values ``{"done": True}``)."""
        ...


class Unsupported(UsageError):
    """The command does not exist for this protocol or series."""


# --------------------------------------------------------------------------- native


def _native_match(shape: native.Shape, address: int) -> Match:
    command, data_size = shape.command, shape.data_size

    def match(frame: Frame) -> Answer | None:
        if not isinstance(frame, native.NativeFrame) or frame.address != address:
            return None
        if frame.command != command or len(frame.data) != data_size:
            return None
        try:
            values = native.interpret(frame, direction=native.Direction.ANSWER).values
        except FrameError as exc:
            return Answer({}, ok=False, detail=f"bad frame: {exc}")
        ok = values.get("result", "success") != "failure"
        return Answer(values, ok, "" if ok else "the sensor answered failure")

    return match


@dataclass(frozen=True, slots=True)
class _NativeSteps:
    """Builds one sensor's native exchanges, by the document's command names."""

    series: Series
    address: int

    def __call__(self, name: str, effect: Effect = Effect(), answer_address: int | None = None,
                 **values: Any) -> Exchange:
        command = native.COMMANDS_BY_NAME[name]
        if not self.has(name):
            raise Unsupported(f"{self.series.name} has no {name} ({command.section})")
        shape = command.answer_for(self.series)
        assert shape is not None
        request = native.encode_request(name, self.address, **values)
        at = self.address if answer_address is None else answer_address
        return Exchange(name, request, shape.length_byte + 1, _native_match(shape, at), effect)

    def has(self, name: str) -> bool:
        return self.series in native.COMMANDS_BY_NAME[name].request.series

    def if_has(self, name: str) -> list[Exchange]:
        return [self(name)] if self.has(name) else []


NativeRow = Callable[[_NativeSteps, Mapping[str, Any]], list[Exchange]]

#: How each catalogue command goes over the native protocol: one row per command, by
#: the document's own command names (``native.COMMANDS``, with their sections).
NATIVE_COMMANDS: Mapping[str, NativeRow] = MappingProxyType({
    "set_zero_type": lambda ex, a: [ex("set_zero_type", zero_type=a["type"])],
    "save": lambda ex, a: [ex("save", Effect(busy_for=SAVE_SECONDS))],
    "calibrate_gyro": lambda ex, a: [ex("calibrate_gyro")],
    "clear_heading": lambda ex, a: [ex("clear_heading")],
    "set_relative_heading": lambda ex, a: [ex("set_relative_heading", degrees=a["degrees"])],
    "set_declination": lambda ex, a: [ex("set_declination", degrees=a["degrees"])],
    "mag_calibration": lambda ex, a: [ex(f"{a['action']}_mag_calibration")],
    # the answer comes from the new address (2.10)
    "set_address": lambda ex, a: [ex("set_address", Effect(new_address=a["address"]),
                                     a["address"], new_address=a["address"])],
    # answered at the old rate, then the line switches (2.4)
    "set_baudrate": lambda ex, a: [ex("set_baudrate", Effect(new_baud=a["baudrate"]),
                                      baudrate=a["baudrate"])],
    "read_settings": lambda ex, a: [ex("read_zero_type"), *ex.if_has("read_declination")],
})


class NativeAdapter:
    wire = Wire.NATIVE

    def new_framer(self) -> native.NativeFramer:
        return native.NativeFramer()

    def garbage_seen(self, framer: Framer) -> int:
        assert isinstance(framer, native.NativeFramer)
        return framer.stats.garbage_bytes + framer.stats.bad_checksums

    def gap_before_request(self, baud: int) -> float:
        return 0.0  # the native protocol frames by its sync byte and length

    def _exchange(self, series: Series, address: int, name: str, effect: Effect = Effect(),
                  answer_address: int | None = None, **values: Any) -> Exchange:
        return _NativeSteps(series, address)(name, effect, answer_address, **values)

    def poll(self, series: Series, address: int) -> Exchange:
        return self._exchange(series, address, "read_all")

    def carries(self, name: str) -> bool:
        return name in NATIVE_COMMANDS

    def command(self, series: Series, address: int, name: str,
                args: Mapping[str, Any]) -> list[Exchange]:
        row = NATIVE_COMMANDS.get(name)
        if row is None:
            raise Unsupported(f"no native command {name!r}")
        return row(_NativeSteps(series, address), args)

    def stream_start(self, series: Series, address: int, hz: float) -> list[Exchange]:
        """2.16 then 2.17: stream the combined frame (2.13-2.15) at ``hz``."""
        if hz not in native.OUTPUT_RATE_CODES.values():
            rates = sorted(native.OUTPUT_RATE_CODES.values())
            raise Unsupported(f"native auto-output rates are {rates}, not {hz}")
        type_code = next(c for c, cmd in native.OUTPUT_TYPES[series].items() if cmd == "read_all")
        return [
            self._exchange(series, address, "set_output_type", output_type=type_code),
            self._exchange(series, address, "set_output_rate", rate_hz=int(hz)),
        ]

    def stream_stop(self, series: Series, address: int) -> list[Exchange]:
        return [self._exchange(series, address, "set_output_rate", rate_hz=0)]

    def unsolicited(self, frame: Frame, series: Series, address: int) -> Answer | None:
        shape = native.COMMANDS_BY_NAME["read_all"].answer_for(series)
        assert shape is not None
        return _native_match(shape, address)(frame)


# --------------------------------------------------------------------------- Modbus


def poll_span(series: Series) -> tuple[int, int]:
    """The registers one poll reads: the IMU measures accel and gyro only (0x28-0x33),
    every other series reads the whole float block (one FC03 of 32)."""
    if series is Series.IMU:
        return rtu.REGISTERS_BY_ADDRESS[0x28].address, 12
    return rtu.FLOAT_BLOCK_START, rtu.FLOAT_BLOCK_COUNT


def _exception_answer(msg: rtu.ExceptionAnswer) -> Answer:
    return Answer({"exception": msg.code}, ok=False, detail=f"Modbus exception {msg.code:02X}")


def _rtu_read_match(unit: int, start: int, count: int) -> Match:
    def match(msg: Frame) -> Answer | None:
        if isinstance(msg, native.NativeFrame) or msg.unit != unit:
            return None
        if isinstance(msg, rtu.ReadResponse) and len(msg.registers) == count:
            return Answer(rtu.read_values(start, msg.registers))
        if isinstance(msg, rtu.ExceptionAnswer) and msg.function == READ_HOLDING:
            return _exception_answer(msg)
        return None

    return match


def _write_answer(reg: rtu.SensorRegister, raw: int) -> Answer:
    """The echo of a write to ``reg``, its value decoded.  A gyro calibration's says
    how far it got (Modbus 2.11): 1 is complete, so the busy period the exchange asks
    for is void (``NO_EFFECT``); 0 is started, and so is any other value (the longer
    wait is the safe reading).  The value itself is passed on as the sensor sent it."""
    answer = Answer({"value": rtu.decode_value(reg, raw)})
    if reg.answer is rtu.WriteAnswer.STARTED_THEN_DONE and raw == rtu.GYRO_CAL_COMPLETE:
        return Answer(answer.values, effect=NO_EFFECT)
    return answer


def _rtu_write_match(unit: int, register: int) -> Match:
    def match(msg: Frame) -> Answer | None:
        if isinstance(msg, native.NativeFrame) or msg.unit != unit:
            return None
        if isinstance(msg, rtu.WriteRegister) and msg.address == register:
            return _write_answer(rtu.REGISTERS_BY_ADDRESS[register], msg.value)
        if isinstance(msg, rtu.ExceptionAnswer) and msg.function == WRITE_SINGLE:
            return _exception_answer(msg)
        return None

    return match


def _never(_: Frame) -> Answer | None:
    return None


class ModbusAdapter:
    wire = Wire.MODBUS

    def new_framer(self) -> rtu.RtuFramer:
        return rtu.RtuFramer(requests=False)

    def garbage_seen(self, framer: Framer) -> int:
        assert isinstance(framer, rtu.RtuFramer)
        return framer.stats.garbage_bytes + framer.stats.bad_crcs

    def gap_before_request(self, baud: int) -> float:
        return rtu_silence(baud)

    def read(self, label: str, unit: int, start: int, count: int) -> Exchange:
        return Exchange(label, rtu.read_request(unit, start, count), 5 + 2 * count,
                        _rtu_read_match(unit, start, count))

    def write(self, series: Series, unit: int, name: str, value: Any,
              effect: Effect = Effect(), answer_unit: int | None = None) -> Exchange:
        reg = rtu.WRITABLE.get(name)
        if reg is None or series not in reg.series:
            raise Unsupported(f"{series.name} over Modbus has no {name} register")
        request = rtu.write_request(unit, name, value)
        if reg.answer is rtu.WriteAnswer.NONE:
            return Exchange(name, request, 0, _never, effect)
        match = _rtu_write_match(unit if answer_unit is None else answer_unit, reg.address)
        return Exchange(name, request, len(request), match, effect)

    def poll(self, series: Series, address: int) -> Exchange:
        start, count = poll_span(series)
        return self.read("poll", address, start, count)

    def raw(self, unit: int, pdu: bytes) -> Exchange:
        """A request PDU passed to the sensor unchanged; the answer's PDU comes back as
        ``values["pdu"]`` (the sensor's exceptions included).  ``pdu`` must be an
        FC03/04/06/16 request the caller has checked."""
        function = pdu[0]
        address, quantity = int.from_bytes(pdu[1:3], "big"), int.from_bytes(pdu[3:5], "big")
        reads = function in (READ_HOLDING, READ_INPUT)
        answer_bytes = 5 + 2 * quantity if reads else 8

        def answers_this(msg: rtu.RtuMessage) -> bool:
            """Only the answer to *this* request: a late answer to an earlier one (other
            registers, another count) must not be passed off as it."""
            match msg:
                case rtu.ExceptionAnswer(_, fn, _):
                    return fn == function
                case rtu.ReadResponse(_, registers, fn):
                    return reads and fn == function and len(registers) == quantity
                case rtu.WriteRegister(_, addr, value):
                    return function == WRITE_SINGLE and addr == address and value == quantity
                case rtu.WriteRegistersResponse(_, addr, count):
                    return function == WRITE_MULTIPLE and (addr, count) == (address, quantity)
            return False

        def match(msg: Frame) -> Answer | None:
            if isinstance(msg, native.NativeFrame) or msg.unit != unit or \
                    not answers_this(msg):
                return None
            return Answer({"pdu": rtu.encode(msg)[1:-2]})

        return Exchange("pass-through", rtu.encode_pdu(unit, pdu), answer_bytes, match)

    def carries(self, name: str) -> bool:
        return name in MODBUS_COMMANDS

    def command(self, series: Series, address: int, name: str,
                args: Mapping[str, Any]) -> list[Exchange]:
        row = MODBUS_COMMANDS.get(name)
        if row is None:
            raise Unsupported(f"{name} has no Modbus register (the native protocol has it)"
                              if name in NATIVE_COMMANDS else f"no Modbus command {name!r}")
        return row(_ModbusSteps(self, series, address), args)

    def stream_start(self, series: Series, address: int, hz: float) -> list[Exchange]:
        interval = round(1000 / hz)
        if not 10 <= interval <= 0xFFFF:
            raise Unsupported(f"{hz} Hz is an auto-output interval of {interval} ms, not 10-65535")
        return [
            self.write(series, address, "output_registers", poll_span(series)),
            self.write(series, address, "output_interval_ms", interval),
        ]

    def stream_stop(self, series: Series, address: int) -> list[Exchange]:
        return [self.write(series, address, "output_interval_ms", 0)]

    def unsolicited(self, frame: Frame, series: Series, address: int) -> Answer | None:
        if isinstance(frame, native.NativeFrame) or frame.unit != address:
            return None
        if isinstance(frame, rtu.WriteRegister) and frame.address == \
                rtu.WRITABLE["calibrate_gyro"].address and frame.value == rtu.GYRO_CAL_COMPLETE:
            return Answer({"done": True})
        start, count = poll_span(series)
        return _rtu_read_match(address, start, count)(frame)


@dataclass(frozen=True, slots=True)
class _ModbusSteps:
    """Builds one sensor's Modbus exchanges, by the document's register names."""

    adapter: ModbusAdapter
    series: Series
    unit: int

    def __call__(self, name: str, value: Any, effect: Effect = Effect(),
                 answer_unit: int | None = None) -> Exchange:
        return self.adapter.write(self.series, self.unit, name, value, effect, answer_unit)

    def read(self, label: str, start: int, count: int) -> Exchange:
        return self.adapter.read(label, self.unit, start, count)


ModbusRow = Callable[[_ModbusSteps, Mapping[str, Any]], list[Exchange]]

#: How each catalogue command goes over Modbus RTU: one row per command, by the
#: document's register names (``modbus_rtu.REGISTERS``).  The declination and the
#: magnetometer calibration have no register (native 2.21-2.26 only): no row.
MODBUS_COMMANDS: Mapping[str, ModbusRow] = MappingProxyType({
    "set_zero_type": lambda w, a: [w("set_zero_type", a["type"])],
    "save": lambda w, a: [w("save", 0, Effect(busy_for=SAVE_SECONDS))],
    "calibrate_gyro": lambda w, a: [w("calibrate_gyro", 0, Effect(busy_until_done=True,
                                                                  read_while_busy=True))],
    "clear_heading": lambda w, a: [w("clear_heading", 0)],
    "set_relative_heading": lambda w, a: [w("set_relative_heading", a["degrees"])],
    "set_address": lambda w, a: [w("set_address", a["address"], Effect(new_address=a["address"]),
                                   answer_unit=a["address"])],
    # never answered (2.3): switch the line, then prove the sensor is there
    "set_baudrate": lambda w, a: [w("set_baudrate", a["baudrate"], Effect(new_baud=a["baudrate"])),
                                  w.read("verify", 0x04, 1)],
    "read_settings": lambda w, a: [w.read("read_settings", 0x04, 2)],
})


def adapter_for(wire: Wire) -> ProtocolAdapter:
    return NativeAdapter() if wire is Wire.NATIVE else ModbusAdapter()
