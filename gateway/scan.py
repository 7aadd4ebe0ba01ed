"""``imu-gateway scan``: which sensors are on this port, at which rate and address?

A one-shot tool for a field engineer, so it talks to the port directly (the gateway
must not be running on it).  For each baud rate, most likely first:

* native: the 2.6 address query ``77 04 00 1F 23`` is answered by any sensor, so one
  request finds a lone sensor; when the answer is garbled (several sensors answering
  at once) every address is asked for its zero type instead.  The combined read
  (0x59) then tells the series by the answer's shape: IMU 0x84/LEN 0x16, VG or MINS
  0x59/0x2F (the protocol cannot tell those two apart), AH 0x59/0x38.
* Modbus: every unit 1-247 is asked for register 0x04 (its product address); a
  sensor that answers is read once more (the float block) to guess its series from
  which values are zero.

Nothing is written to a sensor: only reads and the address query are sent.  Each
request waits its wire time plus ``margin`` for an answer: by default the gateway's own
first timeout (``bus.timing.RTO_INITIAL``), generous enough for a sensor that answers
40 ms late behind a USB adapter's 16 ms latency timer.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import serial

from .bus.timing import RTO_INITIAL
from .model import CAPABILITIES, Protocol, Series
from .normalise import GROUP_FIELDS
from .protocol import modbus_rtu as rtu
from .protocol import native
from .protocol.exchanges import NativeAdapter, char_time, poll_span, rtu_silence

#: Baud rates in the order they are tried: the factory default first, then the rates
#: the documents recommend for fast output, then the rest.
BAUD_ORDER = (9600, 115200, 460800, 19200, 38400, 57600, 4800, 2400)
NATIVE_ADDRESSES = range(256)


@dataclass(frozen=True, slots=True)
class Found:
    protocol: Protocol
    baudrate: int
    address: int
    series: str  # "AH", "VG or MINS", … or "unknown"

    def line(self) -> str:
        return (f"{self.protocol.name.lower():6} {self.baudrate:6} baud  "
                f"address {self.address:3}  series {self.series}")


class Prober:
    """Requests and the frames that come back, with a per-request time budget."""

    def __init__(self, port: serial.Serial, margin: float) -> None:
        self.port = port
        self.margin = margin

    def ask(self, request: bytes, answer_bytes: int, framer: Any, gap: float = 0.0,
            all_answers: bool = False) -> tuple[list[Any], int]:
        """Send ``request``; return the frames heard and how many bytes arrived.  With
        ``all_answers`` it listens for the whole time allowed, not just the first."""
        c = char_time(self.port.baudrate)
        time.sleep(gap)
        self.port.reset_input_buffer()
        self.port.write(request)
        deadline = time.monotonic() + (len(request) + answer_bytes) * c + gap + self.margin
        frames: list[Any] = []
        heard = 0
        while time.monotonic() < deadline and (all_answers or not frames):
            self.port.timeout = max(0.0, deadline - time.monotonic())
            data = self.port.read(max(1, self.port.in_waiting))
            heard += len(data)
            frames += framer.feed(data)
        return frames, heard


def _native_series(prober: Prober, address: int) -> str:
    exchange = NativeAdapter().poll(Series.VG, address)  # the request is the same for all
    frames, _ = prober.ask(exchange.request, native.MAX_FRAME,
                           native.NativeFramer(native.ANSWER_SHAPES))
    for frame in frames:
        if frame.address != address:
            continue
        key = (frame.command, len(frame.data) + 4)
        for series, label in ((Series.IMU, "IMU"), (Series.VG, "VG or MINS"), (Series.AH, "AH")):
            shape = native.COMMANDS_BY_NAME["read_all"].answer_for(series)
            if shape is not None and shape.key == key:
                return label
    return "unknown"


def scan_native(prober: Prober, addresses: Iterable[int]) -> Iterator[tuple[int, str]]:
    query = native.encode_request("read_address")
    # Every sensor answers the address query: listen for all of them (they may answer
    # one after another without colliding).
    frames, heard = prober.ask(query, 6, native.NativeFramer(native.ANSWER_SHAPES),
                               all_answers=True)
    answers = sorted({native.interpret(f).values["address"] for f in frames
                      if f.command == 0x1F})
    if answers and heard == 6 * len(answers):
        found = answers
    elif heard:  # something answered, garbled: several sensors at once
        zero_type = native.COMMANDS_BY_NAME["read_zero_type"]
        found = []
        for address in addresses:
            request = native.encode_request("read_zero_type", address)
            shape = zero_type.answer_for(Series.VG)
            assert shape is not None
            frames, _ = prober.ask(request, shape.length_byte + 1,
                                   native.NativeFramer(native.ANSWER_SHAPES))
            if any(f.address == address for f in frames):
                found.append(address)
    else:
        return
    for address in found:
        yield address, _native_series(prober, address)


def _modbus_series(prober: Prober, unit: int) -> str:
    start, count = poll_span(Series.AH)
    gap = rtu_silence(prober.port.baudrate)
    frames, _ = prober.ask(rtu.read_request(unit, start, count), 5 + 2 * count,
                           rtu.RtuFramer(requests=False), gap)
    for frame in frames:
        if isinstance(frame, rtu.ReadResponse) and frame.unit == unit:
            values = rtu.read_values(start, frame.registers)
            measured = {g for g, (_, members) in GROUP_FIELDS.items()
                        if any(values.get(n) for n in members)}
            # A series leaves what it does not measure at zero: the smallest series
            # whose groups cover what is non-zero is the best guess.
            for series, label in ((Series.IMU, "IMU"), (Series.VG, "VG or MINS"),
                                  (Series.AH, "AH")):
                if measured <= CAPABILITIES[series].groups:
                    return f"{label} (guessed from its values)"
    return "unknown"


def scan_modbus(prober: Prober, units: Iterable[int]) -> Iterator[tuple[int, str]]:
    gap = rtu_silence(prober.port.baudrate)
    for unit in units:
        frames, _ = prober.ask(rtu.read_request(unit, 0x04, 1), 7,
                               rtu.RtuFramer(requests=False), gap)
        if any(getattr(f, "unit", None) == unit for f in frames):
            yield unit, _modbus_series(prober, unit)


def scan(port: str, protocols: Iterable[Protocol], bauds: Iterable[int],
         addresses: Iterable[int] | None = None, margin: float = RTO_INITIAL,
         progress: Callable[[str], None] | None = None) -> Iterator[Found]:
    """Every sensor that answers, as it is found.  Raises ``serial.SerialException``
    when the port cannot be opened."""
    with serial.serial_for_url(port, baudrate=9600, timeout=0.1,
                               exclusive=None if "://" in port else True) as ser:
        prober = Prober(ser, margin)
        for baud in bauds:
            ser.baudrate = baud
            for protocol in protocols:
                if progress:
                    progress(f"{protocol.name.lower()} at {baud} baud")
                if protocol is Protocol.NATIVE:
                    found = scan_native(prober, addresses or NATIVE_ADDRESSES)
                else:
                    units = [a for a in (addresses or rtu.UNIT_IDS) if a in rtu.UNIT_IDS]
                    found = scan_modbus(prober, units)
                for address, series in found:
                    yield Found(protocol, baud, address, series)

