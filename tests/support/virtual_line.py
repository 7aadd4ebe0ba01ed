"""The bus schedule against simulated sensors in virtual time: no pty, no clock.

``VirtualLine`` drives ``imu_gateway.bus.schedule.Schedule`` exactly as the bus master
does (``next_request`` / ``receive`` / ``handle_timer`` / ``next_wake``), with the
simulator's sans-IO sensors (``SimSensor.hear`` / ``due``) on a modelled wire: each
byte takes 10 bits at the line's rate, a sensor's answer starts after its own
turnaround, frames from two senders that meet on the wire are garbled.

A busy machine is modelled too: ``late()`` is how late the driver gets round to each
of its wake-ups (a timer, or bytes from the reader), in seconds.  Bytes that came in
meanwhile wait in the port, where ``handle_timer`` can see them (``pending``).

Everything the driver would write is recorded, so a test can say what went out and
when; ``overlaps`` counts requests written while a sensor was answering or about to.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from imu_gateway.bus.events import Event, Finished, Job, Note, Publish, StateChange
from imu_gateway.bus.schedule import Schedule
from imu_gateway.commands import Command
from imu_gateway.config import BusConfig, config_from_dict
from imu_gateway.model import WireProtocol
from imu_gateway.protocol.exchanges import adapter_for, char_time
from imu_gateway.simulator import SimSensor, make_sensor
from imu_gateway.simulator.sensor import Outgoing


def bus(protocol: str, sensors: list[dict[str, Any]], baudrate: int = 115200,
        **options: Any) -> BusConfig:
    return config_from_dict({"gateway_id": "t", "buses": [
        {"name": "line", "port": "/dev/null", "protocol": protocol, "baudrate": baudrate,
         "sensors": sensors, **options}]}, env={}).buses[0]


def sim(protocol: str, series: str, address: int, *, delay: float = 0.002,
        jitter: float = 0.0, seed: int = 0, baud: int = 115200,
        keep_gap: bool = True) -> SimSensor:
    from imu_gateway.model import Series
    return make_sensor(WireProtocol[protocol.upper()], Series[series], address, baud=baud,
                       answer_delay=delay, jitter=jitter, seed=seed, keep_gap=keep_gap)


@dataclass(slots=True)
class _OnWire:
    start: float
    end: float
    data: bytes
    sender: str
    baud: int


@dataclass
class VirtualLine:
    config: BusConfig
    sensors: list[SimSensor]
    late: Callable[[], float] = lambda: 0.0
    #: how long a frame's bytes stay invisible even to the port's buffer after they
    #: came (the kernel's own work deferred on a busy machine): nothing can see them
    hidden: Callable[[], float] = lambda: 0.0
    #: how long the driver is kept from writing a request it was handed (preempted
    #: between the decision and the write, or in the write): past the request's
    #: ``latest`` it is withdrawn, as the bus master does; otherwise it goes out that
    #: much later, and the driver does nothing else until then
    stall: Callable[[], float] = lambda: 0.0
    withdrawn: int = 0
    #: how long the driver is held after its check of the request's ``latest``, in the
    #: write (the write goes all the same, that much later); ``held_late``: the writes
    #: that so went past their ``latest`` (some still clear of the next frame)
    held: Callable[[], float] = lambda: 0.0
    held_late: int = 0
    now: float = 0.0
    schedule: Schedule = field(init=False)
    events: list[Event] = field(default_factory=list)
    writes: list[tuple[float, bytes]] = field(default_factory=list)
    #: each request's write time and when the bus may first look for its whole answer
    looks: list[tuple[float, float]] = field(default_factory=list)
    overlaps: int = 0
    collisions: int = 0
    _queue: list[Outgoing] = field(default_factory=list)
    _wire: list[_OnWire] = field(default_factory=list)
    # bytes in, not yet received: (data, when the port shows them, when the reader
    # hands them over)
    _port: list[tuple[bytes, float, float]] = field(default_factory=list)
    _driver_at: float = 0.0
    _driver_free: float = 0.0  # a driver held in a write does nothing else until then
    _line_end: float = 0.0  # when the wire is free of the last frame
    _spins: int = 0

    def __post_init__(self) -> None:
        self.schedule = Schedule(self.config, adapter_for(self.config.protocol))
        self.schedule.open(self.now)
        self.schedule.start(self.now)

    # ------------------------------------------------------------ user side

    def command(self, sensor: str, name: str, **args: Any) -> Job:
        assert self.schedule.refusal(sensor) is None
        self._driver_at = self.now  # the driver is woken by a new job
        return self.schedule.command(sensor, Command(name, args))

    def read(self, sensor: str) -> tuple[Job, bool]:
        self._driver_at = self.now
        return self.schedule.read(sensor)

    def lose_port(self) -> None:
        self.schedule.lost(self.now, "the adapter was pulled")
        self.events += self.schedule.take_events()

    def result(self, job: Job) -> Finished | None:
        return next((e for e in self.events if isinstance(e, Finished) and e.job is job), None)

    def readings(self, sensor: str) -> list[Publish]:
        return [e for e in self.events if isinstance(e, Publish) and e.sensor == sensor]

    def notes(self, text: str) -> list[str]:
        return [e.text for e in self.events if isinstance(e, Note) and text in e.text]

    def states(self, sensor: str) -> list[StateChange]:
        return [e for e in self.events if isinstance(e, StateChange) and e.sensor == sensor]

    def writes_to(self, request: bytes) -> int:
        return sum(data == request for _, data in self.writes)

    # ------------------------------------------------------------ time

    def run(self, seconds: float, until: Callable[[], bool] | None = None) -> None:
        end = self.now + seconds
        while self.now < end and not (until is not None and until()):
            self._step(end)

    def _step(self, end: float) -> None:
        frame_end = min((o.end for o in self._wire), default=float("inf"))
        frame_start = min((o.not_before for o in self._queue), default=float("inf"))
        # (a stalled sensor's stream stays due, and says nothing: not a reason to wake)
        streams = min((t for s in self.sensors if (t := s.next_wakeup()) is not None
                       and t > self.now), default=float("inf"))
        self.now = max(self.now, min(self._driver_at, frame_end, frame_start, streams, end))
        for s in self.sensors:
            self._queue += s.due(self.now)
        self._start_frames()
        self._arrive()
        if self.now >= self._driver_at:
            self._drive()

    def _start_frames(self) -> None:
        for out in sorted((o for o in self._queue if o.not_before <= self.now),
                          key=lambda o: o.not_before):
            self._queue.remove(out)
            start = max(out.not_before, self._line_end)
            end = start + len(out.frame) * char_time(out.baud)
            for other in self._wire:
                if other.sender != out.sender and other.end > start:
                    self.collisions += 1
                    other.data = bytes(len(other.data))  # garbled: zeros are no frame
                    out = Outgoing(bytes(len(out.frame)), out.not_before, out.baud,
                                   out.solicited, out.sender)
            self._line_end = max(self._line_end, end)
            self._wire.append(_OnWire(start, end, out.frame, out.sender, out.baud))

    def _arrive(self) -> None:
        for frame in [o for o in self._wire if o.end <= self.now]:
            self._wire.remove(frame)
            data = frame.data if frame.baud == self.schedule.baud else bytes(len(frame.data))
            # The bytes show in the port when the kernel has moved them there; the
            # reader thread hands them over, and the driver runs, when the machine lets
            # them: until then they wait in the port.
            visible = self.now + self.hidden()
            handed = visible + self.late()
            self._port.append((data, visible, handed))
            self._driver_at = max(self._driver_free, min(self._driver_at, handed))

    # ------------------------------------------------------------ the driver

    def _drive(self) -> None:
        s = self.schedule
        for data, at, _ in [p for p in self._port if p[2] <= self.now]:
            s.receive(data, at)
        self._port = [p for p in self._port if p[2] > self.now]
        pending = sum(len(p[0]) for p in self._port if p[1] <= self.now)
        s.handle_timer(self.now, pending)
        self._write(s.next_request(self.now, pending))
        self.events += s.take_events()
        wake = s.next_wake(self.now, pending)
        # A schedule that asks to be woken now, again and again, for nothing, would spin
        # the bus thread: that is a bug, and it fails the test here.
        self._spins = self._spins + 1 if wake <= self.now else 0
        assert self._spins < 1000, f"the schedule spins at {self.now:.6f} s"
        self._driver_at = max(self._driver_free, min(
            [max(wake, self.now + 1e-6) + self.late(),
             *(p[2] for p in self._port)]))  # bytes still on their way

    def _write(self, request: Any) -> None:
        if request is None:
            return
        at = self.now + self.stall()
        if at > request.latest:
            self.schedule.withdraw()
            self.withdrawn += 1
            return
        at += self.held()
        self.held_late += at > request.latest
        # (a stalled write is heard later; whether it meets a frame is judged at the
        # decision's time, when a frame on the wire is surely an overlap)
        if self._wire or any(o.solicited for o in self._queue) or any(
                o.not_before < at + len(request.data) * char_time(self.schedule.baud)
                for o in self._queue):
            self.overlaps += 1
        self.writes.append((self.now, request.data))
        self.looks.append((at, at + request.look_after if request.look_after else 0.0))
        self.schedule.written(at)  # the driver, back from the write, says when
        self._driver_free = at
        heard_at = at + len(request.data) * char_time(self.schedule.baud)
        for sensor in self.sensors:
            data = request.data if sensor.baud == self.schedule.baud else \
                bytes(len(request.data))
            self._queue += sensor.hear(data, heard_at, after_silence=True)


def jittery(seed: int, most: float) -> Callable[[], float]:
    """A busy machine: each wake-up up to ``most`` seconds late, at random."""
    rng = random.Random(seed)
    return lambda: rng.uniform(0, most)
