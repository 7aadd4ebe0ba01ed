"""What the configured rates ask of each serial line, against what it can carry.

The arithmetic of the wire: a character is 10 bits at 8N1, so an exchange takes
(request + answer bytes) x 10 / baud, plus the silent gap before each request (Modbus
RTU: 3.5 characters, 1.75 ms above 19200 baud), plus the sensor's own answer delay.
A stream frame takes its bytes x 10 / baud and nothing else.  A sensor polled flat out
(``poll_hz: 0``) takes what is left, so it asks for nothing here.

Next to a streaming sensor, every other exchange must fit the pause between two of
its frames (the bus master never starts a poll that would meet the next frame), with
the margin the master keeps for the frames' own wobble.  One that cannot fit is
named: it would be polled only right after a frame, and meet the next one.

The answer delay is not known before the sensor answers (``/api/v1/buses`` shows the
learned one); ``ASSUMED_DELAY`` is the fast end of what sensors show, so a warning
here is certain, and a line near 1 may be over once the real delays are known.
"""

from __future__ import annotations

from dataclasses import dataclass

from .bus.line import stream_margin
from .config import BusConfig, SensorConfig
from .protocol.exchanges import adapter_for, char_time

#: A sensor's answer delay assumed for the sums (5-40 ms is common; 2 ms is fast).
ASSUMED_DELAY = 0.002


@dataclass(frozen=True, slots=True)
class Demand:
    """One sensor's share of its line: ``rate`` exchanges (or frames) a second, each
    taking ``wire`` seconds on the wire and ``delay`` seconds of gap and turnaround."""

    sensor: str
    mode: str  # "poll", "stream" or "flat out"
    rate: float
    wire: float
    delay: float

    @property
    def load(self) -> float:
        return self.rate * (self.wire + self.delay)

    @property
    def exchange(self) -> float:
        """One exchange (or frame) on the line, seconds."""
        return self.wire + self.delay


@dataclass(frozen=True, slots=True)
class LineLoad:
    bus: str
    baud: int
    demands: tuple[Demand, ...]

    @property
    def load(self) -> float:
        """The fraction of the line's time the configured rates ask for."""
        return sum(d.load for d in self.demands)

    @property
    def over(self) -> bool:
        return self.load > 1.0

    def describe(self) -> str:
        wire = sum(d.rate * d.wire for d in self.demands)
        delay = sum(d.rate * d.delay for d in self.demands)
        asks = ", ".join(f"{d.sensor} {d.rate:g}/s ({d.mode})" if d.mode != "flat out"
                         else f"{d.sensor} flat out" for d in self.demands)
        return (f"bus {self.bus} at {self.baud} baud: {asks}: wire {wire:.2f} s/s + gaps "
                f"and answer delays {delay:.2f} s/s = {self.load:.2f} of the line")

    def advice(self) -> str:
        return (f"bus {self.bus}: the configured rates ask {self.load:.2f} times what "
                f"{self.baud} baud carries, so sensors will fall short of their rates: "
                "lower poll_hz or stream_hz, raise the baud rate, or split the sensors "
                "over two lines")

    def warnings(self) -> list[str]:
        """What the operator should change: an overloaded line, and exchanges that fit
        no pause of the line's stream."""
        out = [self.advice()] if self.over else []
        stream = next((d for d in self.demands if d.mode == "stream"), None)
        if stream is None:
            return out
        period = 1 / stream.rate
        pause = period - stream.wire - stream_margin(period)
        out += [f"bus {self.bus}: {d.sensor}'s exchange ({d.exchange * 1000:.1f} ms, with a "
                f"fast sensor's answer delay) does not fit the pauses of {stream.sensor}'s "
                f"{stream.rate:g} Hz stream ({pause * 1000:.1f} ms, after the margin for its "
                f"frames' wobble): its polls would go right after a frame and meet the "
                f"next; raise the baud rate, lower stream_hz, or put {d.sensor} on another "
                f"line"
                for d in self.demands if d is not stream and d.exchange > pause]
        return out


def _demand(sensor: SensorConfig, bus: BusConfig) -> Demand:
    adapter = adapter_for(bus.protocol)
    exchange = adapter.poll(sensor.series, sensor.address)
    char = char_time(bus.baudrate)
    if sensor.stream_hz:
        return Demand(sensor.name, "stream", sensor.stream_hz,
                      exchange.answer_bytes * char, 0.0)
    gap = adapter.gap_before_request(bus.baudrate)
    wire = (len(exchange.request) + exchange.answer_bytes) * char
    mode = "poll" if sensor.poll_hz else "flat out"
    return Demand(sensor.name, mode, sensor.poll_hz, wire, gap + ASSUMED_DELAY)


def line_loads(buses: list[BusConfig]) -> list[LineLoad]:
    return [LineLoad(b.name, b.baudrate, tuple(_demand(s, b) for s in b.sensors))
            for b in buses]
