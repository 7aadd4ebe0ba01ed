"""The serial link: bytes in, bytes out, nothing else.

pyserial opens device paths and URLs alike (``/dev/ttyUSB0``, ``socket://host:4001``,
``rfc2217://…``, ``loop://``).  A local serial device (a pseudo-terminal too) has a
file descriptor the bus thread's loop (``reactor``) watches: the bytes are read in the
thread that decides what they mean, with no other thread and no hand-over between.  A
port the loop cannot watch (a URL; a descriptor past ``select``'s limit) gets a small
reader thread that does blocking reads and posts each chunk to the loop.  Opening
happens on a helper thread (a network URL may block on connect; the other lines must
not wait for it).  Writes are short (a request is 5-8 bytes) and go straight out from
the loop.  A read or write failure means the port is gone (USB adapter pulled, socket
closed): it is reported once through ``on_lost`` and the link is closed; reopening is
the bus master's decision.

Either way an answer of known length is taken in one piece: it cannot come faster
than the wire, so rather than waking up per byte, the reader sleeps until the rest
could all be in.  What came in a burst counts as in (a late sender catches up at
once); when nothing more comes in the time one more byte would take, the answer was
shorter (an error frame): what is here is handed over.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import threading
import time
import typing
from collections.abc import Callable
from dataclasses import dataclass

import serial
import serial.rs485
import serial.serialposix

from ..errors import LinkError
from ..threads import tighten_timers
from .reactor import BUS_NICE, FD_SETSIZE, Reactor

READ_MAX = 4096
WRITE_TIMEOUT = 0.5  # s: a port that takes no bytes for this long is lost

OnBytes = Callable[[bytes, float], None]
OnLost = Callable[[Exception], None]
OnOpen = Callable[[LinkError | None], None]


class _Reader(typing.Protocol):
    #: When the reader next needs a turn (``math.inf``: none).
    rest_at: float

    def unseen(self) -> int:
        """Bytes read from the port that have not reached ``on_bytes`` yet."""

    def on_timer(self) -> None: ...

    def look_at(self, at: float) -> None:
        """The awaited answer cannot be whole before ``at``: no wake-up for it sooner."""

    def close(self) -> None: ...


class SerialLink:
    """One port, used from the bus thread only (``open`` calls back there too)."""

    def __init__(self, port: str, baudrate: int, *, rs485: bool = False) -> None:
        self.port = port
        self.baudrate = baudrate
        self.rs485 = rs485
        self._serial: serial.Serial | None = None
        self._reader: _Reader | None = None
        self._opening = 0  # the number of the open under way (0: none)
        self._opens = 0
        self.expect = 0  # bytes of the answer now awaited (0: none known)

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    @property
    def watched(self) -> bool:
        """Whether the bus thread's loop reads the port itself (no reader thread)."""
        return isinstance(self._reader, _LoopReader)

    def open(self, reactor: Reactor, on_bytes: OnBytes, on_lost: OnLost,
             on_open: OnOpen) -> None:
        """Open the port on a helper thread; ``on_open(None)`` (or the ``LinkError``)
        follows on the bus thread.  Then received bytes go to ``on_bytes(data, at)``;
        ``at`` is when they came in (``time.monotonic()``), which on a busy machine can
        be well before the loop gets round to them."""
        if self.rs485 and "://" in self.port:
            # pyserial would accept the setting and silently ignore it.
            on_open(LinkError(f"cannot open {self.port}: kernel RS-485 mode needs a local "
                              "serial device, not a URL"))
            return
        self._opens += 1
        number = self._opening = self._opens

        def opened(ser: serial.Serial | None, error: LinkError | None) -> None:
            if number != self._opening:  # closed meanwhile: this open is not wanted
                if ser is not None:
                    with contextlib.suppress(Exception):
                        ser.close()
                return
            self._opening = 0
            if ser is None:
                on_open(error)
                return
            self._serial = ser
            self._start_reader(ser, reactor, on_bytes, on_lost)
            on_open(None)

        def work() -> None:
            try:
                ser = self._open_port()
            except LinkError as exc:
                reactor.post(functools.partial(opened, None, exc))
                return
            if not reactor.post(functools.partial(opened, ser, None)):
                with contextlib.suppress(Exception):  # the bus thread has ended meanwhile
                    ser.close()

        threading.Thread(target=work, name=f"open {self.port}", daemon=True).start()

    def _open_port(self) -> serial.Serial:
        try:
            # (the write timeout: a network port that stops taking bytes is lost, not
            # waited on by the bus thread, which carries every line)
            ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.1,
                                        write_timeout=WRITE_TIMEOUT, do_not_open=True)
            if "://" not in self.port:
                # One owner per line: a second program opening the same device gets a
                # clear "busy" error instead of both reading half of each answer.
                ser.exclusive = True
            if self.rs485:
                # Kernel RS-485 mode: the UART driver switches the transceiver's direction.
                ser.rs485_mode = serial.rs485.RS485Settings()
            ser.open()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"cannot open {self.port}: {exc}") from None
        return ser

    def _start_reader(self, ser: serial.Serial, reactor: Reactor, on_bytes: OnBytes,
                      on_lost: OnLost) -> None:
        def lost(exc: Exception) -> None:
            if self._serial is ser:  # not an earlier open's reader: that port is closed
                self.close()
                on_lost(exc)

        if watchable(ser):
            self._reader = _LoopReader(self, ser, reactor, on_bytes, lost)
        else:
            self._reader = _ThreadReader(self, ser, reactor, on_bytes, lost)

    @property
    def rest_at(self) -> float:
        """When the reader next needs a turn: the rest of an answer could be in."""
        return self._reader.rest_at if self._reader is not None else math.inf

    def on_timer(self, now: float) -> None:
        if self._reader is not None and self._reader.rest_at <= now:
            self._reader.on_timer()

    def take_expect(self) -> int:
        """The awaited answer's length, once: the first bytes after a request take it."""
        expect, self.expect = self.expect, 0
        return expect

    def pending(self) -> int:
        """Bytes that came in but have not reached ``on_bytes`` yet: in the driver's
        buffer, or in the reader's hands (and, with a reader thread, posted to the loop
        and waiting their turn behind the very timer that asks).  A bus master whose
        timer fired late (a busy machine) looks here before it calls an answer
        missing."""
        ser, reader = self._serial, self._reader
        if ser is None or reader is None:
            return 0
        unseen = reader.unseen()
        try:
            return int(ser.in_waiting) + unseen
        except (serial.SerialException, OSError, ValueError, TypeError):
            return unseen

    def write(self, data: bytes, expect: int = 0, look_after: float = 0.0,
              latest: float = math.inf) -> bool:
        """Send ``data``, unless it is later than ``latest`` (monotonic time) by then:
        False, nothing written.  ``expect`` is the length of the answer, when known,
        and it cannot be whole sooner than ``look_after`` seconds from now."""
        self.expect = expect
        if self._serial is None or self._reader is None:
            raise LinkError(f"{self.port} is not open")
        try:
            if isinstance(self._reader, _LoopReader):
                if not self._write_now(self._reader.fd, data, latest):
                    return False
            elif time.monotonic() > latest:
                return False
            else:
                self._serial.write(data)  # (opened with a write timeout: never for ever)
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"writing to {self.port}: {exc}") from None
        if look_after > 0:
            self._reader.look_at(time.monotonic() + look_after)
        return True

    def _write_now(self, fd: int, data: bytes, latest: float) -> bool:
        """Straight to the descriptor (non-blocking, as pyserial opens it).  A request
        is at most a few hundred bytes and a driver's output buffer takes thousands,
        so one that will not take it whole is stuck (hardware flow control held, a hung
        adapter): the port is lost, rather than the bus thread, which carries every
        line, waiting on it.  (pyserial's write adds a select() per request, an eighth
        of the bus thread's system calls, and spins on a full buffer.)

        The deadline is checked here, the last thing before the write: a thread held
        between the check and the write (a CPU quota that ran out, another thread
        holding the interpreter) writes late all the same, and every line of Python
        between the two was a place to be held (in a quarter-core cgroup, 4 requests
        in 30 s met a stream's next frame that way)."""
        try:
            if time.monotonic() > latest:
                return False
            sent = os.write(fd, data)
        except BlockingIOError:
            sent = 0
        if sent < len(data):
            raise LinkError(f"{self.port} takes no more output ({sent} of {len(data)} "
                            "bytes written): flow control held, or the adapter hung")
        return True

    def set_baudrate(self, baudrate: int) -> None:
        self.baudrate = baudrate
        if self._serial is not None:
            try:
                # The request just written must leave the UART at the old rate first.
                self._serial.flush()
                self._serial.baudrate = baudrate
            except (serial.SerialException, OSError, ValueError) as exc:
                raise LinkError(f"setting {self.port} to {baudrate} baud: {exc}") from None

    def close(self) -> None:
        self._opening = 0  # an open under way is not wanted any more
        ser, self._serial = self._serial, None
        if ser is None:
            return
        if self._reader is not None:
            self._reader.close()
            self._reader = None
        with contextlib.suppress(Exception):
            # Output the port never took is dropped first: a tty's close would wait up
            # to its closing_wait (30 s by default) for it, on the bus thread.
            ser.reset_output_buffer()
        with contextlib.suppress(Exception):
            ser.close()


def watchable(ser: serial.Serial) -> bool:
    """Whether the bus thread's loop can watch the port's descriptor itself."""
    return isinstance(ser, serial.serialposix.Serial) and ser.fileno() < FD_SETSIZE


def byte_time(baudrate: int) -> float:
    return 10 / baudrate


class _LoopReader:
    """The bus loop reads the port: one wake-up for a whole answer, no thread."""

    def __init__(self, link: SerialLink, ser: serial.Serial, reactor: Reactor,
                 on_bytes: OnBytes, on_lost: OnLost) -> None:
        self.link, self.reactor = link, reactor
        self.fd: int = ser.fileno()
        self.on_bytes, self.on_lost = on_bytes, on_lost
        self.held = bytearray()  # an answer's first part, until the rest could be in
        self.want = 0
        self.rest_at = math.inf
        reactor.watch(self.fd, self._readable)

    def unseen(self) -> int:
        return len(self.held)

    def _read(self, woken: bool) -> bool:
        """Read what the port has; False once the port failed.  (With pyserial's
        settings a read finds nothing at once, so nothing means a gone device only
        when the descriptor was ``woken`` as readable.)"""
        try:
            data = os.read(self.fd, READ_MAX)
        except BlockingIOError:
            return True
        except OSError as exc:
            self.on_lost(exc)
            return False
        if not data and woken:  # readable with nothing to read: the device is gone
            self.on_lost(LinkError(f"{self.link.port}: the device reports no data"))
            return False
        self.held += data
        return True

    def _readable(self) -> None:
        if not self._read(woken=True):
            return
        self.want = self.link.take_expect()
        if len(self.held) < self.want:
            self.reactor.unwatch(self.fd)
            self._wait_for_rest()
        else:
            self._hand_over()

    def look_at(self, at: float) -> None:
        if self.held or self.rest_at != math.inf:
            return  # bytes of something else are under way: as they come
        self.reactor.unwatch(self.fd)
        self.rest_at = at

    def _wait_for_rest(self) -> None:
        missing = self.want - len(self.held)
        self.rest_at = time.monotonic() + max(missing, 1) * byte_time(self.link.baudrate)

    def on_timer(self) -> None:
        """The rest of an answer could be in, or (nothing held) the whole of it."""
        self.rest_at = math.inf
        before = len(self.held)
        if not self._read(woken=False):
            return
        if not before and self.held:  # a look, and the answer has begun
            self.want = self.link.take_expect()
        if before < len(self.held) < self.want:
            self._wait_for_rest()
            return
        self.reactor.watch(self.fd, self._readable)
        self._hand_over()

    def _hand_over(self) -> None:
        data = bytes(self.held)
        self.held.clear()
        if data:
            self.on_bytes(data, time.monotonic())

    def close(self) -> None:
        self.rest_at = math.inf
        self.reactor.unwatch(self.fd)


@dataclass(slots=True)
class _Flow:
    """Bytes of one open on their way to ``on_bytes``, in counters each written by one
    thread only (so no lock): the reader's (read and not handed over yet; handed to the
    loop in all) and the loop's (taken in all)."""

    in_hand: int = 0
    handed: int = 0
    taken: int = 0


class _ThreadReader:
    """A thread does blocking reads and posts each answer to the loop: for ports whose
    descriptor the loop cannot watch."""

    rest_at = math.inf  # it waits for an answer's rest on its own thread

    def look_at(self, at: float) -> None:
        pass  # its thread waits in a blocking read anyway

    def __init__(self, link: SerialLink, ser: serial.Serial, reactor: Reactor,
                 on_bytes: OnBytes, on_lost: OnLost) -> None:
        self.link, self.ser, self.reactor = link, ser, reactor
        self.on_bytes, self.on_lost = on_bytes, on_lost
        self.flow = _Flow()
        self.closing = threading.Event()
        self.thread = threading.Thread(target=self._run, name=f"serial {link.port}",
                                       daemon=True)
        self.thread.start()

    def unseen(self) -> int:
        flow = self.flow
        return flow.in_hand + max(0, flow.handed - flow.taken)

    def on_timer(self) -> None:
        pass

    def _take(self, data: bytes, at: float) -> None:
        if self.closing.is_set():
            return  # posted before its port was closed: not the reopened port's bytes
        self.flow.taken += len(data)
        self.on_bytes(data, at)

    def _run(self) -> None:
        tighten_timers(BUS_NICE)
        while not self.closing.is_set():
            try:
                data = self._read_answer()
            except Exception as exc:  # any failure of the device means it is gone
                if not self.closing.is_set():
                    self.reactor.post(functools.partial(self.on_lost, exc))
                return
            if data and not self.closing.is_set():
                self.flow.handed += len(data)
                at = time.monotonic()
                self.reactor.post(functools.partial(self._take, data, at))
            self.flow.in_hand = 0

    def _read_answer(self) -> bytes:
        ser, flow = self.ser, self.flow
        data = ser.read(max(1, ser.in_waiting))
        flow.in_hand = len(data)
        expect = self.link.take_expect()
        while data and len(data) < expect:
            time.sleep(max(expect - len(data) - ser.in_waiting, 1) *
                       byte_time(self.link.baudrate))
            more = ser.read(ser.in_waiting)
            if not more:
                break
            data += more
            flow.in_hand = len(data)
        return data

    def close(self) -> None:
        self.closing.set()
        with contextlib.suppress(Exception):
            self.ser.cancel_read()
        if self.thread is not threading.current_thread():
            self.thread.join(1.0)
