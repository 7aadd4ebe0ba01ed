"""Simulated sensors, sans-IO: bytes heard and the time in, frames to send out.

A sensor never touches a port or a clock.  ``hear(data, now)`` is called with the
master's bytes and the moment their last byte finished on the wire; it returns
``Outgoing`` frames with the earliest time each may start.  ``due(now)`` returns
what the sensor sends on its own (auto-output, the "done" of a gyro calibration).
``bus.PtyBus`` turns that into bytes on a pseudo-terminal at the wire's pace.

Both protocols are built on the same protocol modules the gateway uses, so the
simulator can only say what the documents let it say.
"""

from __future__ import annotations

import math
import random
from abc import ABC, abstractmethod
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import Any

from .. import modbus_codes as mc
from ..model import CAPABILITIES, Angles, Reading, Series, WireProtocol
from ..normalise import field_values
from ..protocol import bcd, native
from ..protocol import modbus_rtu as rtu
from ..protocol.errors import FrameError
from ..protocol.exchanges import Framer, char_time, rtu_silence
from .motion import Leaned, Motion, Source, Turned


@dataclass(slots=True)
class Faults:
    """Misbehaviour a test can switch on at any time (also from another thread)."""

    drop_rate: float = 0.0  # probability that an answer is not sent at all
    corrupt_rate: float = 0.0  # probability that one byte of a frame is flipped
    stalled: bool = False  # hears nothing, says nothing (a dead or unplugged sensor)


@dataclass(frozen=True, slots=True)
class Outgoing:
    frame: bytes
    not_before: float
    baud: int  # the rate it is sent at (a native baud change answers at the old rate)
    solicited: bool  # an answer to a request (vs. auto-output)
    sender: str
    #: the answer to a request the pty may have handed over late (``bus.WireWatch``):
    #: what it meets is the rig's doing
    heard_late: bool = False


@dataclass(slots=True)
class Settings:
    """What a sensor would keep after a save."""

    address: int
    baud: int
    zero_type: str = "absolute"
    declination: float = 0.0


@dataclass(slots=True)
class SimSensor(ABC):
    """State and behaviour common to both protocols."""

    series: Series
    settings: Settings
    source: Source = field(default_factory=Motion)
    answer_delay: float = 0.002  # turnaround before an answer starts
    #: Modbus only: wait out RTU's 3.5-character silence before answering, as the
    #: serial-line rule says.  False answers ``answer_delay`` after the request's last
    #: byte, as many real sensors do (0.5 ms at 9600 baud is well inside the gap).
    keep_gap: bool = True
    jitter: float = 0.0  # plus a uniform 0..jitter, drawn per answer from ``rng``
    save_duration: float = 4.0
    gyro_cal_duration: float = 2.0
    faults: Faults = field(default_factory=Faults)
    seed: int = 0
    # live state
    busy_until: float = 0.0
    zero_offset: tuple[float, float] = (0.0, 0.0)  # pitch, roll at the relative zero
    heading_offset: float = 0.0
    stream_interval: float = 0.0  # seconds between auto-output frames, 0 = off
    next_stream: float = 0.0
    gyro_cal_done_at: float | None = None
    #: every write it heard addressed to it (settings, stream set-up or stop), by name:
    #: what lets a test say the gateway wrote nothing nobody asked for
    writes_heard: Counter[str] = field(default_factory=Counter)
    last_answer_end: float = 0.0  # when this sensor's latest answer leaves the wire
    #: the (pitch, roll) the sensor is held at (``lean``), or None: its source's motion
    leaning: tuple[float, float] | None = None
    #: the heading the sensor is turned to (``turn``), or None: its source's
    turning: Turned | None = None
    rng: random.Random = field(init=False)

    protocol: WireProtocol = field(init=False)

    def __post_init__(self) -> None:
        # A negative draw would answer before the delay; NaN or inf would never answer.
        if not 0.0 <= self.jitter < math.inf:
            raise ValueError(f"jitter must be finite and >= 0 seconds, not {self.jitter!r}")
        self.rng = random.Random(self.seed)

    @property
    def name(self) -> str:
        return f"{self.protocol.name.lower()}:{self.series.name}@{self.settings.address}"

    @property
    def address(self) -> int:
        return self.settings.address

    @property
    def baud(self) -> int:
        return self.settings.baud

    def busy(self, now: float) -> bool:
        """Within save's deaf period."""
        return now < self.busy_until

    # ------------------------------------------------------------ answer timing

    def turnaround(self) -> float:
        """The delay of one answer: ``answer_delay`` plus a uniform 0..``jitter``.

        Drawn from the sensor's own seeded ``rng``, so a run is reproducible with its
        seed.  Without jitter nothing is drawn: the fault draws that share ``rng`` stay
        the sequence they were before jitter existed.
        """
        if not self.jitter:
            return self.answer_delay
        return self.answer_delay + self.rng.uniform(0.0, self.jitter)

    def _silence(self) -> float:
        """Quiet the protocol requires before a frame (RTU's 3.5 characters)."""
        return 0.0

    def _answer_start(self, now: float) -> float:
        """When the answer to a request that ended at ``now`` starts (one turnaround is
        drawn).  A sensor answers one request at a time: with jitter a later request
        could otherwise draw a shorter delay and be answered before, or over, the
        previous answer, so it waits until that answer (and the silence after it) ends.
        """
        silence = self._silence()
        return max(now + silence + self.turnaround(), self.last_answer_end + silence)

    # ------------------------------------------------------------ the measured values

    def lean(self, pitch: float | None, roll: float = 0.0) -> None:
        """Hold the sensor at ``pitch`` and ``roll`` (degrees) from its next sample on,
        or (``None``) let it follow its source's motion again.  Every group follows the
        lean (``motion.Leaned``); the heading goes on as the source has it.  A
        ``ValueError`` names a lean out of range, and the sensor stays as it was.

        From another thread, run it on the simulator's loop:
        ``sim.call(sensor.lean, 7.5, 0.0).result(5)``."""
        if pitch is None:
            self.leaning = None
            return
        Leaned(self.source, pitch, roll)  # checks the range
        self.leaning = (float(pitch), float(roll))

    def turn(self, yaw: float | None, rate: float = 0.0, now: float = 0.0) -> None:
        """Turn the sensor to heading ``yaw`` (degrees) at ``now`` (the simulator's
        clock: ``time.monotonic()``), turning on at ``rate`` deg/s (0: held there); or
        (``None``) let the heading follow its source again.  Pitch and roll stay as
        they are (with a lean: the lean's).  A ``ValueError`` names a turn out of range,
        and the sensor stays as it was.

        From another thread: ``sim.call(sensor.turn, 0.0, 90.0, time.monotonic())``."""
        self.turning = None if yaw is None else Turned(self.source, float(yaw), float(rate),
                                                       now)

    @property
    def attitude(self) -> Source:
        """The source with the turn and the lean, if any, applied: what every value
        comes from."""
        source: Source = self.source if self.turning is None else self.turning
        if self.leaning is None:
            return source
        return Leaned(source, *self.leaning)

    def measure(self, now: float, *, every_group: bool = False) -> Reading:
        """What the sensor reports at ``now``: its source through the zero type and the
        heading settings, limited to what the series measures (``every_group``: not
        limited, for the native reads any series answers, such as an IMU's 2.3)."""
        raw = self.attitude.sample(now)
        reading = raw if every_group else raw.only(CAPABILITIES[self.series].groups)
        if reading.angles is not None:
            a = reading.angles
            yaw = a.yaw - self.heading_offset + self.settings.declination
            reading = replace(
                reading,
                angles=Angles(
                    a.pitch - self.zero_offset[0],
                    a.roll - self.zero_offset[1],
                    yaw % 360.0 if math.isfinite(yaw) else yaw,
                ),
            )
        return reading

    def apply_zero_type(self, zero_type: str, now: float) -> None:
        self.settings.zero_type = zero_type
        if zero_type == "relative":
            angles = self.attitude.sample(now).angles
            self.zero_offset = (angles.pitch, angles.roll) if angles else (0.0, 0.0)
        else:
            self.zero_offset = (0.0, 0.0)

    def set_heading(self, degrees: float, now: float) -> None:
        """Make the yaw read ``degrees`` from now on (clear heading is ``0``)."""
        angles = self.attitude.sample(now).angles
        raw_yaw = angles.yaw if angles else 0.0
        self.heading_offset = raw_yaw + self.settings.declination - degrees

    # ------------------------------------------------------------ the bus interface

    def hear(self, data: bytes, now: float, *, after_silence: bool = False) -> list[Outgoing]:
        """Bytes from the master whose last byte left the wire at ``now``.

        ``after_silence``: the line was quiet before them, so a partial frame left from
        earlier noise will never complete and is dropped first (what a real sensor's
        inter-character timeout does).
        """
        if self.faults.stalled:
            return []
        frames: list[Any] = []
        while after_silence and self.framer.pending:
            frames += self.framer.expire()
        frames += self.framer.feed(data)
        out: list[Outgoing] = []
        for message in self._messages(frames):
            if self.busy(now):
                continue  # save in progress: deaf
            if (write := self._write_name(message)) is not None:
                self.writes_heard[write] += 1
            # Drops are decided per message, before the next one is handled: the next
            # answer queues behind this one only if this one is really sent.
            for o in self._handle(message, now):
                if o.solicited and self.rng.random() < self.faults.drop_rate:
                    continue
                if o.solicited:
                    end = o.not_before + len(o.frame) * char_time(o.baud)
                    self.last_answer_end = max(self.last_answer_end, end)
                out.append(o)
        return out

    def due(self, now: float) -> list[Outgoing]:
        """Frames the sensor sends on its own by ``now``."""
        if self.faults.stalled:
            return []
        out: list[Outgoing] = []
        if self.gyro_cal_done_at is not None and now >= self.gyro_cal_done_at:
            self.gyro_cal_done_at = None
            out.extend(self._gyro_cal_done(now))
        if self.stream_interval and now >= self.next_stream and not self.busy(now):
            # A sensor's timer keeps its beat.  This simulator may fall behind it (held
            # off its CPU): the frames it could not send near their time are lost, as
            # if garbled on the wire, not sent late (which no sensor does), and the
            # next one is due on the old phase.
            behind = (now - self.next_stream) // self.stream_interval
            slot = self.next_stream + behind * self.stream_interval
            self.next_stream = slot + self.stream_interval
            if now - slot <= self.stream_interval / 4:
                out.extend(self._stream_frame(now))
        return out

    def next_wakeup(self) -> float | None:
        times = [t for t in (self.gyro_cal_done_at,) if t is not None]
        if self.stream_interval:
            times.append(max(self.next_stream, self.busy_until))
        return min(times) if times else None

    def _send(self, frame: bytes, at: float, *, solicited: bool = True,
              baud: int | None = None) -> Outgoing:
        if self.faults.corrupt_rate and self.rng.random() < self.faults.corrupt_rate:
            i = self.rng.randrange(len(frame))
            frame = frame[:i] + bytes([frame[i] ^ (1 << self.rng.randrange(8))]) + frame[i + 1 :]
        return Outgoing(frame, at, baud or self.baud, solicited, self.name)

    @property
    @abstractmethod
    def framer(self) -> Framer: ...

    @abstractmethod
    def _messages(self, frames: list[Any]) -> list[Any]: ...

    @abstractmethod
    def _handle(self, message: Any, now: float) -> list[Outgoing]: ...

    @abstractmethod
    def _write_name(self, message: Any) -> str | None:
        """The name of the write ``message`` is, if it is one addressed to this sensor."""

    @abstractmethod
    def _stream_frame(self, now: float) -> list[Outgoing]: ...

    @abstractmethod
    def _gyro_cal_done(self, now: float) -> list[Outgoing]: ...


def _bcd_formats() -> dict[str, bcd.BcdFormat]:
    """Data field name -> its BCD format (the AH combined answer has every data field)."""
    shape = native.COMMANDS_BY_NAME["read_all"].answer_for(Series.AH)
    assert shape is not None
    return {f.name: f.codec.fmt for f in shape.fields if isinstance(f.codec, native.Bcd)}


_DATA_FORMATS = _bcd_formats()


def _clamp(name: str, value: float) -> float:
    """A value a BCD field cannot carry saturates, as a sensor's output does."""
    if not math.isfinite(value):
        return 0.0
    fmt = _DATA_FORMATS[name]
    return max(-fmt.max_value, min(fmt.max_value, value))


@dataclass(slots=True)
class NativeSensor(SimSensor):
    """A sensor speaking the native protocol (every command of sections 2.1-2.26)."""

    output_type: int = 0  # 2.16: the default auto-output is the three angles
    _framer: native.NativeFramer = field(
        default_factory=lambda: native.NativeFramer(native.REQUEST_SHAPES))

    def __post_init__(self) -> None:
        SimSensor.__post_init__(self)
        self.protocol = WireProtocol.NATIVE

    @property
    def framer(self) -> native.NativeFramer:
        return self._framer

    def _messages(self, frames: list[Any]) -> list[native.NativeMessage]:
        messages = []
        for frame in frames:
            try:
                message = native.interpret(frame, direction=native.Direction.REQUEST)
            except FrameError:
                continue
            messages.append(message)
        return messages

    def _data_values(self, command: str, now: float) -> dict[str, float]:
        """The values of the answer to a data read, by the answer shape's field names.
        The shape decides what is sent: 2.1-2.3 and 2.12 name no series, so an IMU
        answers them too, with the attitude its source holds."""
        shape = native.COMMANDS_BY_NAME[command].answer_for(self.series)
        assert shape is not None
        values = field_values(self.measure(now, every_group=True))
        return {f.name: _clamp(f.name, values.get(f.name, 0.0)) for f in shape.fields}

    def _write_name(self, message: native.NativeMessage) -> str | None:
        command = _REQUESTS[message.shape.key]
        if message.address != self.address or command.name.startswith("read_"):
            return None
        return command.name

    def _handle(self, message: native.NativeMessage, now: float) -> list[Outgoing]:
        command = _REQUESTS[message.shape.key]
        if not command.any_address and message.address != self.address:
            return []
        if self.series not in command.request.series:
            return []  # a command this series lacks goes unanswered
        old_baud = self.baud
        at = self._answer_start(now)  # also times save's deaf period and the first frame
        args = message.values
        answer: dict[str, Any] = {}
        match command.name:
            case "read_pitch" | "read_roll" | "read_angles" | "read_accel" | "read_gyro" \
                    | "read_quaternion" | "read_mag" | "read_all":
                answer = self._data_values(command.name, now)
            case "set_baudrate":
                # 2.4: answers at the old rate; a code the table lacks is refused (FF)
                known = args["baudrate"] in native.BAUD_CODES.values()
                if known:
                    self.settings.baud = args["baudrate"]
                answer = {"result": "success" if known else "failure"}
            case "set_address":
                self.settings.address = args["new_address"]  # 2.5: answers from the new one
                answer = {"result": "success"}
            case "read_address":
                answer = {"address": self.address}
            case "save":
                self.busy_until = at + self.save_duration
                answer = {"result": "success"}
            case "set_zero_type":
                self.apply_zero_type(args["zero_type"], now)
                answer = {"result": "success"}
            case "read_zero_type":
                answer = {"zero_type": self.settings.zero_type}
            case "set_output_type":
                # 2.16 answers 00 whatever was asked; a type the series' table lacks is
                # refused with FF (the document is silent there: our choice)
                known = args["output_type"] in native.OUTPUT_TYPES[self.series]
                if known:
                    self.output_type = args["output_type"]
                answer = {"result": "success" if known else "failure"}
            case "set_output_rate":
                hz = args["rate_hz"]
                self.stream_interval = 1 / hz if hz else 0.0
                self.next_stream = at
                answer = {"result": "success"}
            case "calibrate_gyro":
                answer = {"code": 1}
            case "clear_heading":
                self.set_heading(0.0, now)
            case "set_relative_heading":
                self.set_heading(args["degrees"], now)
                answer = dict(args)
            case "set_declination":
                self.settings.declination = args["degrees"]
                answer = dict(args)
            case "read_declination":
                answer = {"declination": self.settings.declination}
            case "start_mag_calibration" | "finish_mag_calibration" | "clear_mag_calibration":
                answer = {"result": "success"}
        frame = native.encode_answer(command.name, self.series, self.address, **answer)
        return [self._send(frame, at, baud=old_baud)]

    def _stream_frame(self, now: float) -> list[Outgoing]:
        command = native.OUTPUT_TYPES[self.series][self.output_type]
        frame = native.encode_answer(command, self.series, self.address,
                                     **self._data_values(command, now))
        return [self._send(frame, now, solicited=False)]

    def _gyro_cal_done(self, now: float) -> list[Outgoing]:
        return []  # the native answer (0xA5 01) is immediate; nothing follows


_REQUESTS: dict[tuple[int, int], native.NativeCommand] = {
    c.request.key: c for c in native.COMMANDS
}

_ILLEGAL_FUNCTION, _ILLEGAL_ADDRESS, _ILLEGAL_VALUE = 1, 2, 3


@dataclass(slots=True)
class ModbusSensor(SimSensor):
    """A sensor speaking Modbus RTU: FC03 reads and FC06 writes of document 1.2.

    FC04 and FC16 are not in the document; the simulator answers them with exception
    01 (illegal function), which is what a Modbus device does with a function it lacks.
    """

    output_start: int = 0x01  # 2.13 defaults: register 0x01, two registers
    output_count: int = 2
    _framer: rtu.RtuFramer = field(default_factory=lambda: rtu.RtuFramer(requests=True))

    def __post_init__(self) -> None:
        SimSensor.__post_init__(self)
        self.protocol = WireProtocol.MODBUS

    @property
    def framer(self) -> rtu.RtuFramer:
        return self._framer

    def _messages(self, frames: list[Any]) -> list[rtu.RtuMessage]:
        return frames

    def registers(self, now: float) -> dict[int, int]:
        """The register file as read now.  Registers of groups the series does not
        measure read zero."""
        values: dict[str, Any] = {r.name: 0.0 for r in rtu.READABLE}
        values |= field_values(self.measure(now))
        values["product_address"] = self.address
        values["zero_type"] = self.settings.zero_type
        return rtu.register_image(
            {r.name: values[r.name] for r in rtu.READABLE}
        )

    def _silence(self) -> float:
        return rtu_silence(self.baud) if self.keep_gap else 0.0

    def _write_name(self, message: rtu.RtuMessage) -> str | None:
        if message.unit not in (self.address, 0):
            return None
        if isinstance(message, rtu.WriteRegister | rtu.WriteRegisters):
            return f"register 0x{message.address:02X}"
        return None

    def _handle(self, message: rtu.RtuMessage, now: float) -> list[Outgoing]:
        if message.unit not in (self.address, 0):
            return []
        broadcast = message.unit == 0  # executed, never answered
        at = self._answer_start(now)  # also times save's deaf period and the first frame
        answer: rtu.RtuMessage | None
        match message:
            case rtu.ReadRequest(_, start, count, mc.READ_HOLDING):
                if not rtu.is_readable_span(start, count):
                    answer = rtu.ExceptionAnswer(self.address, 3, _ILLEGAL_ADDRESS)
                else:
                    image = self.registers(now)
                    answer = rtu.ReadResponse(
                        self.address, tuple(image[a] for a in range(start, start + count))
                    )
            case rtu.WriteRegister(_, address, value):
                answer = self._write(address, value, now, at)
            case rtu.ReadRequest() | rtu.WriteRegisters():
                function = mc.READ_INPUT if isinstance(message, rtu.ReadRequest) \
                    else mc.WRITE_MULTIPLE
                answer = rtu.ExceptionAnswer(self.address, function, _ILLEGAL_FUNCTION)
            case _:
                answer = None  # an answer from another device: not for us
        if answer is None or broadcast:
            return []
        return [self._send(rtu.encode(answer), at)]

    def _write(self, address: int, value: int, now: float,
               at: float) -> rtu.RtuMessage | None:
        """Carry out an FC06 heard at ``now`` and return its answer (``None``: none is
        sent); ``at`` is when the answer would start."""
        reg = rtu.REGISTERS_BY_ADDRESS.get(address)
        if reg is None or not reg.writable or self.series not in reg.series:
            return rtu.ExceptionAnswer(self.address, 6, _ILLEGAL_ADDRESS)
        if reg.accepts is not None and value not in reg.accepts:
            return rtu.ExceptionAnswer(self.address, 6, _ILLEGAL_VALUE)
        decoded = rtu.decode_value(reg, value)
        echo = rtu.WriteRegister(self.address, address, value)
        match reg.name:
            case "set_zero_type":
                self.apply_zero_type(decoded, now)
            case "set_baudrate":
                self.settings.baud = decoded  # 2.3: no answer, effective at once
                return None
            case "set_address":
                self.settings.address = value  # 2.7: the echo comes from the new address
                return rtu.WriteRegister(self.address, address, value)
            case "save":
                self.busy_until = at + self.save_duration
            case "calibrate_gyro":
                # 2.11: 0 = started, "done" follows; a sensor that is done at once
                # (``gyro_cal_duration`` 0) answers 1 = complete, and nothing follows
                if self.gyro_cal_duration <= 0:
                    return rtu.WriteRegister(self.address, address, rtu.GYRO_CAL_COMPLETE)
                self.gyro_cal_done_at = now + self.gyro_cal_duration
                return rtu.WriteRegister(self.address, address, rtu.GYRO_CAL_STARTED)
            case "output_interval_ms":
                if 0 < value < 10:
                    return rtu.ExceptionAnswer(self.address, 6, _ILLEGAL_VALUE)
                self.stream_interval = value / 1000
                self.next_stream = at
            case "output_registers":
                start, count = decoded
                if not (1 <= count <= rtu.MAX_READ and rtu.is_readable_span(start, count)):
                    return rtu.ExceptionAnswer(self.address, 6, _ILLEGAL_VALUE)
                self.output_start, self.output_count = start, count
            case "clear_heading":
                self.set_heading(0.0, now)
            case "set_relative_heading":
                self.set_heading(decoded, now)
        return echo

    def _stream_frame(self, now: float) -> list[Outgoing]:
        image = self.registers(now)
        span = range(self.output_start, self.output_start + self.output_count)
        frame = rtu.encode(rtu.ReadResponse(self.address, tuple(image[a] for a in span)))
        return [self._send(frame, now, solicited=False)]

    def _gyro_cal_done(self, now: float) -> list[Outgoing]:
        reg = rtu.WRITABLE["calibrate_gyro"]
        frame = rtu.encode(rtu.WriteRegister(self.address, reg.address, rtu.GYRO_CAL_COMPLETE))
        return [self._send(frame, now, solicited=False)]


def make_sensor(protocol: WireProtocol, series: Series, address: int | None = None,
                baud: int = 9600, **options: Any) -> SimSensor:
    """A simulated sensor with the protocol's default address (native 0, Modbus 1).

    ``options`` are ``SimSensor``'s fields, e.g. ``answer_delay=0.005, jitter=0.035``
    (seconds) for answers 5-40 ms late.
    """
    cls: type[SimSensor] = NativeSensor if protocol is WireProtocol.NATIVE else ModbusSensor
    if address is None:
        address = 0 if protocol is WireProtocol.NATIVE else 1
    return cls(series, Settings(address, baud), **options)
