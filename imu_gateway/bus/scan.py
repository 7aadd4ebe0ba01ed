"""A scan: which sensors are on this port, at which rate and address?

Used by ``imu-gateway scan`` (``tools/scan.py``) and by REST's ``POST /api/v1/scan``
(``scanning.py``).  It talks to the port directly: a port one of the gateway's own
buses uses is released by that bus for the scan (``PortKeeper.pause``).  For each baud
rate, most likely first:

* native: the 2.6 address query ``77 04 00 1F 23`` is answered by any sensor, so one
  request finds a lone sensor; when the answer is garbled (several sensors answering
  at once) every address is asked for its zero type instead, unless bytes with no
  frame's start among them keep coming unasked too (a sensor streaming at another
  rate: at this one it is noise, and every address would be asked through it in
  vain; ``Prober.unreadable_traffic``).  A query that heard only part of one answer
  (fewer bytes than an answer: a lone sensor's answer cut short, not several at once)
  is asked once more first, and its clean answers taken.  The combined read
  (0x59) then tells the series by the answer's shape: IMU 0x84/LEN 0x16, VG or MINS
  0x59/0x2F (the protocol cannot tell those two apart), AH 0x59/0x38.
* Modbus: every unit 1-247 (248-255 too with ``all_addresses``) is asked for register
  0x04 (its product address); a sensor that answers is read once more (the float
  block) to guess its series from which values are zero.

A streaming sensor (auto-output, which a paused bus's sensor keeps up) sends frames
nobody asked for.  They are not answers: a request waits for the frame it asked for
(its command, from its address) and listens through the others.  Nor are they a
collision: the address query's answers are judged garbled by the bytes that are not
a complete frame, so a stream's frames do not send the scan asking every address one
by one.  A stream frame cut short by the request (its first bytes dropped with the
input buffer) looks garbled: the query is then asked again right after one of the
stream's frames, in the pause before the next (``Prober.after_a_frame``); so is every
request after that at that rate, which keeps the answers from meeting the stream's
frames on the wire (at the cost of up to one stream period per request).

Nothing is written to a sensor: only reads and the address query are sent.  Each
request waits its wire time plus ``margin`` for an answer: by default the gateway's own
first timeout (``bus.timing.RTO_INITIAL``), generous enough for a sensor that answers
40 ms late behind a USB adapter's 16 ms latency timer.  That wait is also what the
progress reports' estimate of the time left is made of (``time_left``).
"""

from __future__ import annotations

import errno
import functools
import math
import os
import time
from collections.abc import Callable, Generator, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import serial

from ..modbus_codes import READ_HOLDING
from ..model import CAPABILITIES, VALUE_GROUPS, Series, WireProtocol
from ..protocol import modbus_rtu as rtu
from ..protocol import native
from ..protocol.exchanges import NativeAdapter, char_time, poll_span, rtu_silence
from .timing import RTO_INITIAL

#: Baud rates in the order they are tried: the factory default first, then the rates
#: the documents recommend for fast output, then the rest.
BAUD_ORDER = (9600, 115200, 460800, 19200, 38400, 57600, 4800, 2400)
NATIVE_ADDRESSES = range(256)
#: Units Modbus reserves, which the config refuses, but which a sensor's address
#: register (0x00-0xFF in the document) can be set to by another tool.  Unit 0 is not
#: among them on purpose: it is broadcast, which a device carries out without
#: answering, so a read sent to it can never find anything.
RESERVED_UNITS = range(248, 256)

#: The wire sizes of the requests a sweep makes, which ``Prober.ask`` and the estimate
#: of the time left both go by.
_QUERY = native.encode_request("read_address")
_QUERY_ANSWER_BYTES = 6
_ZERO_TYPE_REQUEST_BYTES = len(native.encode_request("read_zero_type", 0))
_UNIT_REQUEST_BYTES = len(rtu.read_request(1, 0x04, 1))  # FC03 of register 0x04
_UNIT_ANSWER_BYTES = 7  # unit, function, byte count, one register, CRC

#: The address query, garbled beside a stream, is asked this many times in all.
QUERY_TRIES = 5
#: A request beside a stream whose answer came garbled is sent this many times in all.
STREAM_TRIES = 5
#: A sensor found (it answered) is asked what it is this many times at most before
#: its series is "unknown": one answer missed (a busy machine, a pseudo-terminal's
#: late hand-over) must not leave a found sensor nameless.
IDENTIFY_TRIES = 3
#: Waiting for a stream's frame to go right after it: no longer than this (a stream
#: slower than once a second is asked past, as a quiet line is).
STREAM_WAIT = 1.0

#: What opening a port someone else holds fails with: EAGAIN (EWOULDBLOCK) from the
#: flock pyserial's ``exclusive=True`` takes, as the gateway's does; EBUSY when the
#: holder set TIOCEXCL on the tty.
BUSY_ERRNOS = frozenset({errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY})


def _zero_type_answer_bytes() -> int:
    shape = native.COMMANDS_BY_NAME["read_zero_type"].answer_for(Series.VG)
    assert shape is not None
    return int(shape.length_byte) + 1


def listen_time(baud: int, request_bytes: int, answer_bytes: int, margin: float,
                gap: float = 0.0) -> float:
    """How long after its silent gap a request may wait for its answer: both frames'
    wire time, the silence the sensor needs to see the request end (RTU), ``margin``."""
    return (request_bytes + answer_bytes) * char_time(baud) + gap + margin


@dataclass(frozen=True, slots=True)
class Found:
    protocol: WireProtocol
    baudrate: int
    address: int
    series: str  # "AH", "VG or MINS", … or "unknown"

    def line(self) -> str:
        return (f"{self.protocol.name.lower():6} {self.baudrate:6} baud  "
                f"address {self.address:3}  series {self.series}")


@dataclass(frozen=True, slots=True)
class Step:
    """One protocol at one baud rate, and the addresses it may ask one by one."""

    protocol: WireProtocol
    baudrate: int
    addresses: tuple[int, ...]

    def address_time(self, margin: float) -> float:
        """The longest one address's request takes (when nothing answers)."""
        if self.protocol is WireProtocol.NATIVE:
            return listen_time(self.baudrate, _ZERO_TYPE_REQUEST_BYTES,
                               _zero_type_answer_bytes(), margin)
        gap = rtu_silence(self.baudrate)
        return gap + listen_time(self.baudrate, _UNIT_REQUEST_BYTES, _UNIT_ANSWER_BYTES,
                                 margin, gap)

    def start_time(self, margin: float) -> float:
        """The step's time when nothing answers: native, the address query alone (the
        addresses are asked one by one only when several sensors answer it); Modbus,
        every unit."""
        if self.protocol is WireProtocol.NATIVE:
            return listen_time(self.baudrate, len(_QUERY), _QUERY_ANSWER_BYTES, margin)
        return len(self.addresses) * self.address_time(margin)


def time_left(steps: Sequence[Step], index: int, left: int | None, margin: float) -> float:
    """Seconds the scan still takes if nothing more answers: step ``index`` from its
    start (``left`` None) or with ``left`` addresses still to ask one by one, then every
    later step.  Answers end requests early and each sensor found costs one more read,
    so it is an estimate, not a bound."""
    step = steps[index]
    here = step.start_time(margin) if left is None else left * step.address_time(margin)
    return here + sum(later.start_time(margin) for later in steps[index + 1:])


def modbus_units(addresses: Iterable[int] | None = None,
                 all_addresses: bool = False) -> list[int]:
    """The units a Modbus sweep asks, in order: 1-247, with ``all_addresses`` 248-255
    too; ``addresses`` narrows them.  Never 0 (see ``RESERVED_UNITS``)."""
    allowed = range(1, RESERVED_UNITS.stop) if all_addresses else rtu.UNIT_IDS
    return sorted({a for a in (addresses or allowed) if a in allowed})


def plan(protocols: Iterable[WireProtocol], bauds: Iterable[int],
         addresses: Iterable[int] | None = None, all_addresses: bool = False) -> list[Step]:
    """The steps of a scan, in the order they are taken."""
    native_addresses = tuple(sorted(set(addresses or NATIVE_ADDRESSES)))
    units = tuple(modbus_units(addresses, all_addresses))
    return [Step(protocol, baud, native_addresses if protocol is WireProtocol.NATIVE else units)
            for baud in dict.fromkeys(bauds) for protocol in dict.fromkeys(protocols)]


@dataclass(frozen=True, slots=True)
class Progress:
    """Where a scan is: a step starting (``address`` None), or about to ask ``address``,
    the ``asked + 1``-th of the step's addresses."""

    step: Step
    address: int | None
    asked: int
    seconds_left: float

    def line(self) -> str:
        step = self.step
        left = f"about {_duration(self.seconds_left)} left"
        if self.address is not None:
            where = f"address {self.address} ({self.asked + 1} of {len(step.addresses)}; {left})"
        elif step.protocol is WireProtocol.NATIVE:
            where = f"address query ({left})"
        else:
            count = len(step.addresses)
            where = f"{count} address{'es' if count != 1 else ''} ({left})"
        return f"scanning {step.protocol.name.lower()} {step.baudrate} baud, {where}"


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1, math.ceil(seconds))} s"
    # To 10 s: finer would claim a precision the estimate does not have, coarser would
    # leave the line unchanged for a minute.
    minutes, rest = divmod(round(seconds / 10) * 10, 60)
    return f"{minutes} min {rest} s" if rest else f"{minutes} min"


class Throttle:
    """Passes each step's start on, and then at most one report every ``interval``
    seconds: a sign of life for whoever waits, not 247 lines a minute."""

    def __init__(self, report: Callable[[Progress], None], interval: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._report = report
        self._interval = interval
        self._clock = clock
        self._last = -math.inf

    def __call__(self, progress: Progress) -> None:
        now = self._clock()
        if progress.address is None or now - self._last >= self._interval:
            self._last = now
            self._report(progress)


#: Told the address about to be asked and how many of the step's were asked before.
Tick = Callable[[int, int], None]


def _no_tick(address: int, asked: int) -> None:
    pass


def _anything(frame: Any) -> bool:
    return True


def _wire_size(frame: Any) -> int:
    if isinstance(frame, native.NativeFrame):
        return len(frame.data) + 5  # 77, LEN, address, command, data, checksum
    return len(rtu.encode(frame))


@dataclass(frozen=True, slots=True)
class Heard:
    """What came back to a request: the frames it asked for; how many complete frames
    came that it did not ask for (a stream's); and ``noise``, the bytes that were not
    one of those (the answers' own, garbage, a frame cut short)."""

    answers: list[Any]
    unasked: int
    noise: int


class Prober:
    """Requests and the frames that come back, with a per-request time budget."""

    def __init__(self, port: serial.Serial, margin: float) -> None:
        self.port = port
        self.margin = margin
        #: Frames nobody asked for were heard at this rate (a stream): each request
        #: goes right after one of them, not into the next (``after_a_frame``).
        self.stream = False
        #: Until then (``time.monotonic()``) a request that went unanswered may still
        #: be answered, a margin late; whoever writes to the line next waits for it.
        self.quiet_at = 0.0

    def wait_quiet(self) -> None:
        time.sleep(max(0.0, self.quiet_at - time.monotonic()))

    def ask(self, request: bytes, answer_bytes: int, framer: Callable[[], Any],
            gap: float = 0.0, all_answers: bool = False,
            wanted: Callable[[Any], bool] = _anything) -> Heard:
        """Send ``request``; return what came back (``framer`` makes the framer of the
        answers).  It waits for the first frame that is ``wanted`` (the others, a
        stream's, are heard through); with ``all_answers`` it listens for the whole
        time allowed.  Beside a stream, a request whose answer came garbled (met a
        stream frame: on a busy machine the request may go late) is sent again."""
        for _ in range(STREAM_TRIES if self.stream and not all_answers else 1):
            heard = self._ask(request, answer_bytes, framer(), gap, all_answers, wanted)
            if heard.answers or not heard.noise:
                break
        return heard

    def _ask(self, request: bytes, answer_bytes: int, framer: Any, gap: float,
             all_answers: bool, wanted: Callable[[Any], bool]) -> Heard:
        if self.stream:
            self.after_a_frame()
        time.sleep(gap)
        self.port.reset_input_buffer()
        self.port.write(request)
        deadline = time.monotonic() + listen_time(self.port.baudrate, len(request),
                                                  answer_bytes, self.margin, gap)
        # A frame coming in as the time runs out (a stream's, most likely) is waited
        # for, once: cut off, its bytes would look like a collision.
        grace = native.MAX_FRAME * char_time(self.port.baudrate)
        answers: list[Any] = []
        unasked: list[Any] = []
        heard = 0
        while all_answers or not answers:
            left = deadline - time.monotonic()
            if left <= 0:
                if not getattr(framer, "pending", 0) or not grace:
                    break
                deadline, grace = deadline + grace, 0.0
                continue
            self.port.timeout = left
            data = self.port.read(max(1, self.port.in_waiting))
            heard += len(data)
            for frame in framer.feed(data):
                (answers if wanted(frame) else unasked).append(frame)
        self.stream = self.stream or (bool(unasked) and isinstance(framer, native.NativeFramer))
        if not answers:
            self.quiet_at = time.monotonic() + self.margin
        return Heard(answers, len(unasked), heard - sum(map(_wire_size, unasked)))

    def unreadable_traffic(self) -> bool:
        """Whether the line carries, unasked, what this rate cannot read (a sensor
        streaming at another rate: its frames are noise at this one).  After the
        longest a late answer or a collision's tail can still come in (the margin and a
        frame), two windows each as long as a frame and the margin: bytes came in each,
        and no frame's first byte (0x77) among them.  A frame of this rate cut by the
        listen's start is one tail, in one window at most; a frame that starts in the
        windows shows its 0x77."""
        frame = native.MAX_FRAME * char_time(self.port.baudrate)
        window = max(self.margin, frame)
        time.sleep(self.margin + frame)
        self.port.reset_input_buffer()
        return all(self._unreadable_for(window) for _ in range(2))

    def _unreadable_for(self, seconds: float) -> bool:
        end, heard, sync = time.monotonic() + seconds, 0, False
        while (left := end - time.monotonic()) > 0:
            self.port.timeout = left
            data = self.port.read(max(1, self.port.in_waiting))
            heard += len(data)
            sync = sync or native.SYNC in data
        return heard > 0 and not sync

    def after_a_frame(self) -> None:
        """Wait for a native frame to end (at most ``STREAM_WAIT``): a stream's, whose
        next frame is then a period away, the line quiet for a request meanwhile."""
        framer = native.NativeFramer(native.ANSWER_SHAPES)
        self.port.reset_input_buffer()
        end = time.monotonic() + STREAM_WAIT
        while (left := end - time.monotonic()) > 0:
            self.port.timeout = left
            if framer.feed(self.port.read(max(1, self.port.in_waiting))):
                return


_READ_ALL_SHAPES = {
    shape.key: label for series, label in ((Series.IMU, "IMU"), (Series.VG, "VG or MINS"),
                                           (Series.AH, "AH"))
    if (shape := native.COMMANDS_BY_NAME["read_all"].answer_for(series)) is not None}
_ZERO_TYPE_ANSWERS = frozenset(
    shape.key[0] for series in Series
    if (shape := native.COMMANDS_BY_NAME["read_zero_type"].answer_for(series)) is not None)


def _answer_framer() -> native.NativeFramer:
    return native.NativeFramer(native.ANSWER_SHAPES)


def _until_answered(ask: Callable[[], Heard]) -> Heard:
    """``ask()`` again until an answer comes, ``IDENTIFY_TRIES`` times at most."""
    for _ in range(IDENTIFY_TRIES - 1):
        if (heard := ask()).answers:
            return heard
    return ask()


def _native_series(prober: Prober, address: int) -> str:
    exchange = NativeAdapter().poll(Series.VG, address)  # the request is the same for all
    heard = _until_answered(functools.partial(
        prober.ask, exchange.request, native.MAX_FRAME, _answer_framer,
        wanted=lambda f: f.address == address and _shape_key(f) in _READ_ALL_SHAPES))
    return _READ_ALL_SHAPES[_shape_key(heard.answers[0])] if heard.answers else "unknown"


def _shape_key(frame: native.NativeFrame) -> tuple[int, int]:
    return frame.command, len(frame.data) + 4


def _zero_type_from(address: int) -> Callable[[native.NativeFrame], bool]:
    return lambda f: f.address == address and f.command in _ZERO_TYPE_ANSWERS


class Query(NamedTuple):
    """What the 2.6 address query heard."""

    answers: list[int]  # the addresses that answered
    garbled: bool  # bytes that were not a whole frame came too (several answering at once)
    streaming: bool  # frames nobody asked for came (a stream)
    cut: bool  # all it heard was some bytes, fewer than one answer's: one cut short?


def _address_query(prober: Prober) -> Query:
    """The 2.6 query, answered by any sensor.  Beside a stream, a garbled query is
    asked again right after one of its frames."""
    for _ in range(QUERY_TRIES):
        heard = prober.ask(_QUERY, _QUERY_ANSWER_BYTES, _answer_framer, all_answers=True,
                           wanted=lambda f: f.command == 0x1F)
        garbled = heard.noise != _QUERY_ANSWER_BYTES * len(heard.answers)
        if not (garbled and heard.unasked):
            break
    answers = sorted({native.interpret(f).values["address"] for f in heard.answers})
    return Query(answers, garbled, heard.unasked > 0,
                 not (answers or heard.unasked) and 0 < heard.noise < _QUERY_ANSWER_BYTES)


def scan_native(prober: Prober, addresses: Iterable[int],
                tick: Tick = _no_tick) -> Iterator[tuple[int, str]]:
    # Every sensor answers the address query: listen for all of them (they may answer
    # one after another without colliding).
    answers, garbled, streaming, cut = _address_query(prober)
    if garbled and not (answers or streaming) and prober.unreadable_traffic():
        # Not several sensors answering at once: the line carries what this rate
        # cannot read, asked or not.  Asking 256 addresses through it would take the
        # margin each (25 s at the default) and be garbled all the same.
        return
    if cut:
        # Less than one answer's bytes: one answer cut short (a port that handed its
        # end over late), not several at once, which garble at least as many bytes as
        # one.  Asked once more before every address is; taken only if it comes clean.
        again = _address_query(prober)
        if again.answers and not again.garbled:
            answers, garbled, streaming = again.answers, False, again.streaming
    if answers and not garbled:
        found = answers
    elif garbled or streaming:  # several sensors at once; or a stream, not answering
        found = []
        for asked, address in enumerate(addresses):
            tick(address, asked)
            request = native.encode_request("read_zero_type", address)
            heard = prober.ask(request, _zero_type_answer_bytes(), _answer_framer,
                               wanted=_zero_type_from(address))
            if heard.answers:
                found.append(address)
    else:
        return
    for address in found:
        yield address, _native_series(prober, address)


class ReservedUnitAnswers:
    """A framer for FC03 answers from one unit in 248-255.  The shared RTU framer takes
    such a unit byte for noise (no device may use it) and skips it, so the scan checks
    the one answer it waits for itself: re-encoded, the bytes must match, CRC and all."""

    def __init__(self, unit: int) -> None:
        self.unit = unit
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[rtu.ReadResponse]:
        self._buf += data
        buf = self._buf
        for start in range(len(buf) - 4):
            count = buf[start + 2]
            end = start + 5 + count
            if (buf[start] != self.unit or buf[start + 1] != READ_HOLDING or count % 2
                    or not count or end > len(buf)):
                continue
            answer = rtu.ReadResponse(self.unit, tuple(
                int.from_bytes(buf[i:i + 2], "big") for i in range(start + 3, end - 2, 2)))
            if rtu.encode(answer) == buf[start:end]:
                del buf[:end]
                return [answer]
        return []


def _answers_from(unit: int) -> Any:
    return ReservedUnitAnswers(unit) if unit in RESERVED_UNITS else rtu.RtuFramer(
        requests=False)


def _modbus_series(prober: Prober, unit: int) -> str:
    start, count = poll_span(Series.AH)
    gap = rtu_silence(prober.port.baudrate)
    heard = _until_answered(functools.partial(
        prober.ask, rtu.read_request(unit, start, count), 5 + 2 * count,
        functools.partial(_answers_from, unit), gap, wanted=_unit_is(unit)))
    for frame in heard.answers:
        if isinstance(frame, rtu.ReadResponse):
            values = rtu.read_values(start, frame.registers)
            measured = {g for g, spec in VALUE_GROUPS.items()
                        if any(values.get(n) for n in spec.fields)}
            # A series leaves what it does not measure at zero: the smallest series
            # whose groups cover what is non-zero is the best guess.
            for series, label in ((Series.IMU, "IMU"), (Series.VG, "VG or MINS"),
                                  (Series.AH, "AH")):
                if measured <= CAPABILITIES[series].groups:
                    return f"{label} (guessed from its values)"
    return "unknown"


def _unit_is(unit: int) -> Callable[[Any], bool]:
    return lambda frame: bool(getattr(frame, "unit", None) == unit)


def scan_modbus(prober: Prober, units: Iterable[int],
                tick: Tick = _no_tick) -> Iterator[tuple[int, str]]:
    gap = rtu_silence(prober.port.baudrate)
    for asked, unit in enumerate(units):
        tick(unit, asked)
        heard = prober.ask(rtu.read_request(unit, 0x04, 1), _UNIT_ANSWER_BYTES,
                           functools.partial(_answers_from, unit), gap,
                           wanted=_unit_is(unit))
        if heard.answers:
            yield unit, _modbus_series(prober, unit)


def _ticker(progress: Callable[[Progress], None], steps: Sequence[Step], index: int,
            margin: float) -> Tick:
    step = steps[index]

    def tick(address: int, asked: int) -> None:
        left = len(step.addresses) - asked
        progress(Progress(step, address, asked, time_left(steps, index, left, margin)))

    return tick


def _open(port: str) -> serial.Serial:
    try:
        return serial.serial_for_url(port, baudrate=9600, timeout=0.1,
                                     exclusive=None if "://" in port else True)
    except ValueError as exc:  # an unknown URL scheme: bad input, worded like the rest
        raise serial.SerialException(str(exc)) from None


def scan(port: str, protocols: Iterable[WireProtocol], bauds: Iterable[int],
         addresses: Iterable[int] | None = None, margin: float = RTO_INITIAL,
         progress: Callable[[Progress], None] | None = None,
         all_addresses: bool = False) -> Generator[Found, None, None]:
    """Every sensor that answers, as it is found; closing the generator ends the scan
    and frees the port.  Raises ``serial.SerialException`` when the port cannot be
    opened (``port_problem`` words it)."""
    steps = plan(protocols, bauds, addresses, all_addresses)
    with _open(port) as ser:
        prober = Prober(ser, margin)
        try:
            for index, step in enumerate(steps):
                ser.baudrate = step.baudrate
                prober.stream = False  # (a stream at another rate is noise at this one)
                tick: Tick = _no_tick
                if progress:
                    progress(Progress(step, None, 0, time_left(steps, index, None, margin)))
                    tick = _ticker(progress, steps, index, margin)
                scanner = scan_native if step.protocol is WireProtocol.NATIVE else scan_modbus
                for address, series in scanner(prober, step.addresses, tick):
                    yield Found(step.protocol, step.baudrate, address, series)
        finally:
            # A paused bus resumes on the port next: the scan's last request, if it
            # went unanswered, may still be answered into the bus's first.
            prober.wait_quiet()


def port_problem(port: str, exc: serial.SerialException) -> str:
    """One line for a port that cannot be opened or used."""
    code = exc.errno
    if code in BUSY_ERRNOS:
        return (f"{port} is in use by another process: stop the gateway first (it holds "
                f"{port}); `fuser -v {port}` shows who has it")
    if code is not None:  # pyserial's own text says the errno and the port twice
        hint = {errno.ENOENT: " (unplugged? see ls /dev/serial/by-id/)",
                errno.EACCES: " (is your user in the dialout group?)"}.get(code, "")
        return f"cannot open {port}: {os.strerror(code)}{hint}"
    return str(exc) if port in str(exc) else f"{port}: {exc}"
