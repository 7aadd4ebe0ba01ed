"""The simulated RS-485 line: sensors behind a pseudo-terminal, at the wire's pace.

The gateway (or a test with pyserial) opens the pty's slave side like a serial port;
this module holds the master side.  A pty moves bytes instantly, so the wire is
modelled here:

* a request of n bytes written at t is heard by the sensors at t + n·10/baud;
* an answer starts no earlier than the sensor says (its answer delay, plus the RTU
  silent interval) and its bytes are released one by one as each would finish on the
  wire, so a frame of n bytes takes n·10/baud seconds to arrive and arrives in
  realistic pieces;
* the line's baud rate is the one the client set on the slave (read back with
  ``termios``): a sensor at another rate hears noise, and is heard as noise;
* bytes from the master while a sensor is answering, or about to, are an **overlap**:
  counted, reported, and the test that drives a bus master asserts there are none;
* two sensors answering at once (the 2.6 address query with several sensors on a
  line) **collide**: the bytes are mixed and counted.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import dataclasses
import functools
import math
import os
import random
import select
import sys
import termios
import threading
import time
import traceback
import tty
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

from ..protocol.exchanges import char_time
from ..threads import tighten_timers
from .sensor import Outgoing, SimSensor

#: The event loop's timers are good to about a millisecond (epoll); waits shorter than
#: this are done in select(), which keeps the simulated wire's timing to microseconds.
PRECISE = 0.002

#: Even select() wakes late: by Linux's default timer slack (50 µs) plus the scheduler's
#: wake-up latency (another 40-60 µs measured on a 2-core VM).  The wait for an
#: answer's last byte, which decides when the exchange ends, spends its final stretch
#: spinning on the clock instead.
SPIN = 0.00015

#: The simulator thread's niceness where allowed: it plays hardware, which shares the
#: CPU with nothing, and a starved simulator (tests run beside CPU burners) would play
#: a sensor that stops streaming for half a second.
SIM_NICE = -15

#: Held off the CPU this long, the simulator has stopped playing hardware (its loop
#: otherwise wakes within a couple of milliseconds of when it asks, ``WATCH_TICK``).
#: A hold is a silence of ``WATCH_TICK + HELD`` (18 ms) or more.  It must be noticed
#: when it is long enough to make a master's retry meet a late answer: a master waits
#: at least its timeout and the hold after it, 2 x 10 ms, from a request before it
#: sends again, so a simulator held 18 ms behind an answer it gives in 2 ms already
#: answers into the retry.  (At 20 ms, an overlap of that kind went unexplained beside
#: CPU burners: the simulator held about 25 ms, below the threshold of then, 30.)
HELD, WATCH_TICK = 0.008, 0.01
#: Overlaps and collisions this soon after such a hold are its doing: a
#: request read late, or a frame sent late, affects the exchange it belongs to, which
#: is over within a sensor's longest answer timeout (0.4 s).
SHADOW = 0.5

#: The pseudo-terminal hands the master's bytes to this side later, in a kernel
#: worker of normal priority, not in the master's ``write()`` as a UART's driver puts
#: them out.  Beside CPU burners that worker waits its turn: in the soak, requests a
#: master wrote in their place next to a 20 Hz stream were heard 23 and 47 ms later,
#: on the stream's next frame, while the simulator itself ran on time.  A request
#: heard ``LAGGED`` late may have used up the room a master keeps before a stream's
#: frame (at 20 Hz: 6 ms, 1 ms of quiet and a tenth of the period), so what a request
#: heard while the hand-over is this late meets (``WireWatch``) is the rig's doing.
LAGGED = 0.005

T = TypeVar("T")

_SPEEDS = {
    getattr(termios, f"B{rate}"): rate
    for rate in (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
    if hasattr(termios, f"B{rate}")
}


@dataclass(slots=True)
class BusStats:
    requests_bytes: int = 0
    answer_frames: int = 0
    overlaps: int = 0
    collisions: int = 0
    noise_bytes: int = 0
    overrun_bytes: int = 0  # the client did not read and the pty buffer was full
    internal_errors: int = 0  # a bug in a simulated sensor: logged, the line carries on
    events: deque[str] = field(default_factory=lambda: deque(maxlen=200))
    #: the first overlaps and collisions, each with the events that led to it
    incidents: list[list[str]] = field(default_factory=list)
    #: times this simulator was held off its CPU (by the machine: it plays hardware,
    #: which never stops), for how long in all, and the overlaps and collisions that
    #: followed one within ``SHADOW``, or were of a request the pty handed over late
    #: (counted in the totals above too)
    holds: int = 0
    held_s: float = 0.0
    #: times the pty handed the canary over ``LAGGED`` late or more, and for how
    #: long in all (``WireWatch``)
    lags: int = 0
    lagged_s: float = 0.0
    overlaps_after_hold: int = 0
    collisions_after_hold: int = 0
    #: (``watch_port``) times a client opened the line's port, and closed it (the last
    #: of its descriptors: the pty's master sees the hangup)
    port_opens: int = 0
    port_closes: int = 0

    @property
    def masters_overlaps(self) -> int:
        """The overlaps the master is answerable for: not right after a hold."""
        return self.overlaps - self.overlaps_after_hold

    @property
    def masters_collisions(self) -> int:
        return self.collisions - self.collisions_after_hold


def overdue(pending: Sequence[Outgoing], tx_end: float, now: float) -> bool:
    """Whether a request heard at ``now`` meets the ``pending`` answers only because
    the simulator is late with them: nothing is on the wire (``tx_end``), and a
    punctual sensor would have sent each one whole by now (from its ``not_before``).
    A hold of the simulator's thread this short (under ``HELD`` since its last beat)
    escapes ``HoldWatch``; its answer due and unsent shows it all the same."""
    return now >= tx_end and bool(pending) and all(
        now >= o.not_before + len(o.frame) * char_time(o.baud) for o in pending)


class HoldWatch:
    """Notices when the simulator is held off its CPU for ``HELD`` or more.

    Real sensors never stop; a simulator does, when the machine does not run it
    (another process of higher priority, a virtual machine's host taking its CPU
    away).  A request it then reads late looks sent late, and a stream frame goes out
    late: what follows is the rig's doing, and is counted apart.  The simulator beats
    at least every ``WATCH_TICK`` (``run``) and wherever it waits outside its loop
    (its precise waits, byte by byte), so a longer silence is a hold."""

    def __init__(self, stats: BusStats, note: Callable[[str], None]) -> None:
        self.stats = stats
        self.note = note
        self.last_beat = math.inf  # when it last ran (none yet: no hold either)
        self.last_hold_end = -math.inf
        self.on_tick: Callable[[], None] | None = None  # (the port's watch)

    def beat(self) -> None:
        """The simulator is running now: was it held since it last was?"""
        now = time.monotonic()
        held = now - self.last_beat - WATCH_TICK
        self.last_beat = now
        if held >= HELD:
            self.stats.holds += 1
            self.stats.held_s += held
            self.last_hold_end = now
            self.note(f"HELD: the simulator was held {held * 1000:.0f} ms")

    def in_shadow(self) -> bool:
        """Within ``SHADOW`` of a hold, or in one not yet noticed."""
        now = time.monotonic()
        return now - self.last_hold_end < SHADOW or now - self.last_beat > WATCH_TICK + HELD

    async def run(self) -> None:
        self.last_beat = time.monotonic()
        while True:
            await asyncio.sleep(WATCH_TICK)
            self.beat()
            if self.on_tick is not None:
                self.on_tick()


class LineLog:
    """What happened lately on the line, timed, and the incidents with that context;
    overlaps and collisions right after a hold (``HoldWatch``) counted apart."""

    def __init__(self, stats: BusStats, verbose: bool) -> None:
        self.stats = stats
        self.verbose = verbose
        self.holds: HoldWatch | None = None
        self._recent: deque[str] = deque(maxlen=8)

    def note(self, text: str, heard_late: bool = False, overdue: bool = False) -> None:
        """``heard_late``: an incident of a request the pty may have handed over late
        (``WireWatch``), or of its answer; ``overdue``: an overlap only because the
        simulator had not sent an answer yet that a punctual sensor would have sent
        whole by then (``overdue``)."""
        incident = text.startswith(("OVERLAP", "COLLISION"))
        held = self.holds is not None and self.holds.in_shadow()
        if incident and (held or heard_late or overdue):
            if text.startswith("OVERLAP"):
                self.stats.overlaps_after_hold += 1
            else:
                self.stats.collisions_after_hold += 1
            text += " (of a request the pty handed over late)" if heard_late else \
                " (the simulator's answer was overdue: it was held)" if overdue else \
                " (right after the simulator was held)"
        self.timeline(text)
        if incident and len(self.stats.incidents) < 10:
            self.stats.incidents.append(list(self._recent))
        self.stats.events.append(text)

    def timeline(self, text: str) -> None:
        """What happened lately, timed: the context of an incident."""
        self._recent.append(f"{time.monotonic():.4f} {text}")
        if self.verbose:
            print(f"sim: {text}", file=sys.stderr, flush=True)


class PortWatch:
    """(``watch_port``) Who has the line's port open.  The simulator keeps no descriptor
    of the pty's slave side itself, so its master sees a hangup while no client has the
    port open: each open and close is counted (``port_opens``, ``port_closes``) and
    noted."""

    def __init__(self, stats: BusStats, note: Callable[[str], None]) -> None:
        self.stats = stats
        self.note = note
        self.client = False  # a client has the port open now

    def opened(self, master: int) -> bool:
        """(Each ``WATCH_TICK``) True when a client has opened the port since the last
        look: the master's hangup is gone."""
        if self.client or master < 0:
            return False
        hangup = select.poll()
        hangup.register(master, select.POLLIN)
        if any(e & select.POLLHUP for _, e in hangup.poll(0)):
            return False
        self.client = True
        self.stats.port_opens += 1
        self.note("PORT: opened by a client")
        return True

    def closed(self) -> bool:
        """The master read EIO: True when that is the client closing the port."""
        if not self.client:
            return False
        self.client = False
        self.stats.port_closes += 1
        self.note("PORT: closed by its client (hangup)")
        return True


class WireWatch:
    """Notices when the pseudo-terminal hands bytes over ``LAGGED`` late or more.

    The simulator cannot see when the master wrote what it reads.  So it keeps a
    canary: a pseudo-terminal of its own, whose bytes go through the same kernel
    worker as the line's.  Each ``WATCH_TICK`` it writes a byte there (unless one is
    still under way) and times its arrival.  While a canary byte is held that long,
    and right after one came through that late, the worker has been held, and a
    request read then may have been written up to that much earlier (``late``).
    Beside CPU burners the worker is late most of the time (about 1000 times in a
    two-minute soak, 15 ms on average), so it is no blanket excuse: only what a
    request read then meets is.  Sans-IO apart from ``open``, ``close`` and the
    writes: times are arguments."""

    def __init__(self, stats: BusStats, note: Callable[[str], None]) -> None:
        self.stats = stats
        self.note = note
        self.sent_at: float | None = None  # the canary byte under way (None: none)
        self.released_at = -math.inf  # when a canary held ``LAGGED`` or more came through
        self._ends = (-1, -1)  # the canary pty's (master, slave)

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        os.set_blocking(slave, False)
        self._ends = (master, slave)
        loop.add_reader(master, self._readable)

    def close(self, loop: asyncio.AbstractEventLoop) -> None:
        master, slave = self._ends
        if master >= 0:
            loop.remove_reader(master)
            os.close(master)
            os.close(slave)
        self._ends = (-1, -1)
        self.sent_at = None

    def tick(self, now: float) -> None:
        """Send the next canary byte, unless one is under way."""
        if self.sent_at is not None or self._ends[1] < 0:
            return
        with contextlib.suppress(BlockingIOError):
            os.write(self._ends[1], b"\0")
            self.sent_at = now

    def _readable(self) -> None:
        with contextlib.suppress(BlockingIOError):
            os.read(self._ends[0], 64)
        self.arrived(time.monotonic())

    def arrived(self, now: float) -> None:
        """The canary byte came through at ``now``."""
        if self.sent_at is None:
            return
        lag, self.sent_at = now - self.sent_at, None
        if lag >= LAGGED:
            self.stats.lags += 1
            self.stats.lagged_s += lag
            self.released_at = now
            self.note(f"LAGGED: the pty handed bytes over {lag * 1000:.0f} ms late")

    def late(self, now: float) -> bool:
        """Whether bytes read at ``now`` may have been held by the kernel's worker: a
        canary byte is held ``LAGGED`` or more now, or one so held came through less
        than ``LAGGED`` ago (the worker released both; the line's was read second)."""
        return now - self.released_at < LAGGED or \
            (self.sent_at is not None and now - self.sent_at >= LAGGED)


class PtyBus:
    """Several simulated sensors on one pseudo-terminal."""

    def __init__(
        self,
        sensors: Sequence[SimSensor],
        *,
        noise_rate: float = 0.0,
        seed: int = 0,
        link: str | None = None,
        verbose: bool = False,
        on_sent: Callable[[float, bytes, bool], None] | None = None,
        watch_port: bool = False,
    ) -> None:
        """``on_sent(t, frame, solicited)`` is told of every frame a sensor sent, at the
        monotonic time its last byte was written (benchmarks time the path from there).
        ``watch_port``: each open and close of the port is seen (``PortWatch``)."""
        self.watch_port = watch_port
        self.sensors = list(sensors)
        self.on_sent = on_sent
        self.noise_rate = noise_rate  # bursts of line noise per second, while idle
        self.link = link
        self.verbose = verbose
        self.stats = BusStats()
        self.rng = random.Random(seed)
        self._master = -1
        self._slave = -1
        self.path = ""
        self._queue: list[Outgoing] = []
        self._rx_wire_end = 0.0
        self._tx_end = 0.0
        self._wakeup: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.log = LineLog(self.stats, verbose)
        self._holds = self.log.holds = HoldWatch(self.stats, self.log.timeline)
        self.port_watch = PortWatch(self.stats, self.log.note) if watch_port else None
        self._wire = WireWatch(self.stats, self.log.timeline)
        self._holds.on_tick = self._tick

    # ------------------------------------------------------------ the pty

    def open(self) -> str:
        """Create the pseudo-terminal; returns the path clients open.

        Raises ``OSError`` when ``link`` cannot be made (a file that is not our old
        link is in the way, or its folder is missing); nothing is deleted but links.
        """
        if self.link and os.path.lexists(self.link) and not os.path.islink(self.link):
            raise FileExistsError(f"{self.link} exists and is not a symlink; not replacing it")
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        if self.watch_port:  # (the line's rate is read through the master: the same tty)
            os.close(self._slave)
            self._slave = -1
        if self.link:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link)
            try:
                os.symlink(self.path, self.link)
            except OSError:
                self.close()
                raise
        if self._loop is not None and not self.watch_port:
            self._loop.add_reader(self._master, self._on_readable)
        return self.path

    def close(self) -> None:
        if self._master < 0:
            return
        if self._loop is not None:
            self._loop.remove_reader(self._master)
        os.close(self._master)
        if self._slave >= 0:
            os.close(self._slave)
        if self.port_watch is not None:
            self.port_watch.client = False
        self._master = self._slave = -1
        if self.link:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link)

    def unplug(self) -> None:
        """The USB adapter is pulled: the device (and ``link``) disappears."""
        self.close()
        self._queue.clear()

    def replug(self) -> str:
        """The adapter is back; with ``link`` set it is at the same path."""
        return self.open()

    def line_baud(self) -> int:
        """The rate the client set on its side of the line."""
        return _SPEEDS.get(termios.tcgetattr(self._slave if self._slave >= 0
                                             else self._master)[5], 0)

    def _tick(self) -> None:
        """Each ``WATCH_TICK``: the canary goes on, and (``watch_port``) a client's
        bytes are listened to once it has opened the port."""
        self._wire.tick(time.monotonic())
        if self._loop is not None and self.port_watch and self.port_watch.opened(self._master):
            self._loop.add_reader(self._master, self._on_readable)

    # ------------------------------------------------------------ the wire

    def _on_readable(self) -> None:
        self._holds.beat()  # a hold that ends here is noted before what it did to the line
        try:
            data = os.read(self._master, 4096)
        except BlockingIOError:
            return
        except OSError:  # EIO: no client has the port open
            if self.port_watch and self.port_watch.closed() and self._loop is not None:
                self._loop.remove_reader(self._master)
            return
        if not data:
            return
        assert self._loop is not None
        now = self._loop.time()
        baud = self.line_baud()
        pending = [o for o in self._queue if o.solicited]
        late = self._wire.late(time.monotonic())
        if now < self._tx_end or pending:
            self.stats.overlaps += 1
            self.log.note(f"OVERLAP: master sent {data.hex(' ')} while a sensor was answering",
                          heard_late=late, overdue=overdue(pending, self._tx_end, now))
        self.stats.requests_bytes += len(data)
        self.log.timeline(f"master -> {data.hex(' ')}")
        # A gap of more than 3.5 characters ends any frame in progress (RTU's rule; the
        # native sensors' own inter-character timeout is modelled the same way).
        after_silence = now - self._rx_wire_end > 3.5 * char_time(baud or 9600)
        self._rx_wire_end = max(now, self._rx_wire_end) + len(data) * char_time(baud or 9600)
        queued = len(self._queue)
        for sensor in self.sensors:
            heard = data if sensor.baud == baud else _noise(self.rng, len(data))
            self._guarded(sensor, functools.partial(sensor.hear, heard, self._rx_wire_end,
                                                    after_silence=after_silence))
        if late:  # its answers carry the excuse to whatever they meet
            self._queue[queued:] = [dataclasses.replace(o, heard_late=True)
                                    for o in self._queue[queued:]]
        if self._wakeup is not None:
            self._wakeup.set()

    async def _transmit(self, out: Outgoing) -> None:
        assert self._loop is not None
        loop = self._loop
        frame = out.frame
        # Anything else due before this frame would be off the wire collides with it.
        duration = len(frame) * char_time(out.baud)
        # The frame starts when the sensor says, not when this loop got round to it:
        # bytes whose time has passed go out at once (never earlier than the model), so
        # the loop's own lateness does not delay the end of the answer.
        start = max(out.not_before, self._rx_wire_end, self._tx_end)
        for other in [o for o in self._queue if o.not_before < start + duration]:
            if other.sender != out.sender:
                self._queue.remove(other)
                self.stats.collisions += 1
                self.log.note(f"COLLISION: {out.sender} and {other.sender}",
                              heard_late=out.heard_late or other.heard_late)
                frame = bytes(a ^ b for a, b in zip(frame.ljust(len(other.frame), b"\0"),
                                                    other.frame.ljust(len(frame), b"\0"),
                                                    strict=True))
        if out.baud != self.line_baud():
            frame = _noise(self.rng, len(frame))  # heard at the wrong rate: garbage
        c = char_time(out.baud)
        self._tx_end = start + len(frame) * c
        written = 0
        while written < len(frame) and self._master >= 0:
            # A byte is released when its stop bit would have left the wire.
            done = min(len(frame), int((loop.time() - start) / c + 1e-9))
            if done > written:
                try:
                    os.write(self._master, frame[written:done])
                except BlockingIOError:
                    self.stats.overrun_bytes += done - written
                except OSError:  # (watch_port) nobody has the port open: lost
                    if not self.watch_port:
                        raise
                written = done
            if written < len(frame):
                # Only the last byte's release ends the exchange: that wait is exact,
                # earlier pieces may go out a little late.
                last = written + 1 == len(frame)
                await self._pause(start + (written + 1) * c - loop.time(), exact=last)
        self.stats.answer_frames += 1
        if self.on_sent is not None:
            self.on_sent(time.monotonic(), frame, out.solicited)
        self.log.note(f"{out.sender} -> {out.frame.hex(' ')}")

    def _inject_noise(self) -> None:
        burst = _noise(self.rng, self.rng.randint(1, 8))
        self.stats.noise_bytes += len(burst)
        with contextlib.suppress(BlockingIOError):
            os.write(self._master, burst)
        for sensor in self.sensors:
            self._guarded(sensor, functools.partial(
                sensor.hear, burst, self._loop.time() if self._loop else 0.0))

    def _guarded(self, sensor: SimSensor, act: Callable[[], list[Outgoing]]) -> None:
        """Queue what a sensor sends; a bug in it is reported, and the line lives on."""
        try:
            out = act()
            for o in out:
                if o.solicited:
                    self.log.timeline(f"{o.sender} answers from {o.not_before:.4f}")
            self._queue.extend(out)
        except Exception:
            self.stats.internal_errors += 1
            self.log.note(f"INTERNAL ERROR in {sensor.name}")
            print(f"sim: internal error in {sensor.name}:\n{traceback.format_exc()}",
                  file=sys.stderr, flush=True)

    async def serve(self, stop: asyncio.Event | None = None,
                    on_ready: Callable[[], None] | None = None) -> None:
        """Run the line until ``stop`` is set (or forever).  ``on_ready`` is called once
        bytes written to the pty are being listened to."""
        self._loop = asyncio.get_running_loop()
        self._wakeup = asyncio.Event()
        tighten_timers(SIM_NICE)
        if self._master < 0:
            self.open()
        elif not self.watch_port:
            self._loop.add_reader(self._master, self._on_readable)
        if on_ready is not None:
            on_ready()
        stop = stop or asyncio.Event()
        next_noise = self._loop.time() + _noise_gap(self.rng, self.noise_rate)
        self._wire.open(self._loop)
        watch = asyncio.ensure_future(self._holds.run())
        try:
            while not stop.is_set():
                now = self._loop.time()
                if self._master < 0:  # unplugged
                    await self._sleep(stop, 0.05)
                    continue
                for sensor in self.sensors:
                    self._guarded(sensor, functools.partial(sensor.due, now))
                ready = [o for o in self._queue if o.not_before <= now]
                if ready:
                    first = min(ready, key=lambda o: o.not_before)
                    self._queue.remove(first)
                    await self._transmit(first)
                    continue
                if self.noise_rate and now >= next_noise:
                    if now >= self._tx_end and not self._queue:
                        self._inject_noise()
                    next_noise = now + _noise_gap(self.rng, self.noise_rate)
                wakeups = [o.not_before for o in self._queue]
                wakeups += [t for s in self.sensors if (t := s.next_wakeup()) is not None]
                if self.noise_rate:
                    wakeups.append(next_noise)
                await self._sleep(stop, min(wakeups) - now if wakeups else None)
        finally:
            watch.cancel()
            self._wire.close(self._loop)
            self.close()

    async def _pause(self, seconds: float, *, exact: bool = False) -> None:
        if seconds > PRECISE:
            await asyncio.sleep(seconds - PRECISE)
        else:
            self._precise_wait(seconds, exact=exact)

    def _precise_wait(self, seconds: float, *, exact: bool = False) -> None:
        """Wait in ``select()`` on the pty: microsecond timing where the event loop's
        timers round up to a millisecond, and the master's bytes are still handled the
        moment they arrive (so an overlap is seen when it happens).  ``exact``: wake
        ``SPIN`` early and spin to the deadline."""
        if seconds <= 0 or self._master < 0:
            return
        deadline = time.monotonic() + seconds
        listened = [self._master] if self.port_watch is None or self.port_watch.client else []
        ready, _, _ = select.select(listened, [], [],
                                    max(0.0, seconds - SPIN) if exact else seconds)
        self._holds.beat()
        if ready:
            self._on_readable()
            return  # the caller looks again: the line may have changed
        while exact and time.monotonic() < deadline:
            pass

    async def _sleep(self, stop: asyncio.Event, timeout: float | None) -> None:
        if timeout is not None and timeout <= PRECISE:
            self._precise_wait(timeout)
            return
        assert self._wakeup is not None
        self._wakeup.clear()
        waiters = [asyncio.ensure_future(self._wakeup.wait()), asyncio.ensure_future(stop.wait())]
        try:
            # Wake a little early; the caller's next, short wait is a precise one.
            await asyncio.wait(waiters, timeout=None if timeout is None else timeout - PRECISE,
                               return_when=asyncio.FIRST_COMPLETED)
        finally:
            for waiter in waiters:
                waiter.cancel()


def _noise(rng: random.Random, count: int) -> bytes:
    return bytes(rng.randrange(256) for _ in range(count))


def _noise_gap(rng: random.Random, rate: float) -> float:
    """Seconds to the next burst of line noise (``rate`` bursts a second)."""
    return rng.expovariate(rate) if rate else float("inf")


class SimulatorThread:
    """Run a ``PtyBus`` on its own event loop in a background thread.

    For tests and benchmarks: the simulator keeps its own timing whatever the code
    under test does with its loop.  ``with SimulatorThread(sensors) as sim: sim.path``.
    Sensor faults and settings may be changed from the test thread between requests.
    """

    def __init__(self, sensors: Sequence[SimSensor], *, noise_rate: float = 0.0, seed: int = 0,
                 link: str | None = None, verbose: bool = False,
                 watch_port: bool = False) -> None:
        self.bus = PtyBus(sensors, noise_rate=noise_rate, seed=seed, link=link, verbose=verbose,
                          watch_port=watch_port)
        self._thread = threading.Thread(target=self._run, name="simulator", daemon=True)
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._error: BaseException | None = None

    @property
    def path(self) -> str:
        return self.bus.path

    def _run(self) -> None:
        async def main() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            await self.bus.serve(self._stop, on_ready=self._ready.set)

        try:
            asyncio.run(main())
        except BaseException as exc:  # surfaced in __exit__
            self._error = exc
            self._ready.set()

    def call(self, fn: Callable[..., T], *args: object) -> concurrent.futures.Future[T]:
        """Run ``fn(*args)`` on the simulator's loop, between its handling of the line's
        bytes (unplug/replug, a sensor's ``lean``).  The future is done once it has run:
        ``.result(5)`` waits for that and gives what ``fn`` returned, or raises what it
        raised."""
        assert self._loop is not None
        done: concurrent.futures.Future[T] = concurrent.futures.Future()

        def run() -> None:
            try:
                done.set_result(fn(*args))
            except Exception as exc:  # the caller's to see, not the loop's
                done.set_exception(exc)

        self._loop.call_soon_threadsafe(run)
        return done

    def __enter__(self) -> SimulatorThread:
        self._thread.start()
        if not self._ready.wait(10):
            raise TimeoutError("the simulator did not start within 10 s")
        if self._error is not None:
            raise self._error
        return self

    def __exit__(self, *_: object) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)
        if self._error is not None:
            raise self._error


@contextlib.contextmanager
def simulated(sensors: Sequence[SimSensor], **options: Any) -> Iterator[SimulatorThread]:
    """``SimulatorThread`` as a context manager; ``options`` are ``PtyBus``'s."""
    with SimulatorThread(sensors, **options) as sim:
        yield sim
