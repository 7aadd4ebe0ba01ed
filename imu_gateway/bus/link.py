"""The serial link: bytes in, bytes out, nothing else.

pyserial opens device paths and URLs alike (``/dev/ttyUSB0``, ``socket://host:4001``,
``rfc2217://…``, ``loop://``).  Not every one of those has a file descriptor an event
loop could watch, so a small reader thread does blocking reads and hands each chunk
to the loop; writes are short (a request is 5-8 bytes) and go straight out from the
loop.  A read or write failure means the port is gone (USB adapter pulled, socket
closed): it is reported once through ``on_lost`` and the link is closed; reopening is
the bus master's decision.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import serial
import serial.rs485

from ..errors import LinkError
from ..threads import tighten_timers

#: The bus and reader threads' niceness, where the system allows it: a line's timing
#: is the machine's to keep even when other work takes the CPU (the systemd unit can
#: grant CAP_SYS_NICE).
BUS_NICE = -10


@dataclass(slots=True)
class _Flow:
    """Bytes of one open on their way to ``on_bytes``, in counters each written by one
    thread only (so no lock): the reader's (read and not handed over yet; handed to the
    loop in all) and the loop's (taken in all)."""

    in_hand: int = 0
    handed: int = 0
    taken: int = 0


class SerialLink:
    def __init__(self, port: str, baudrate: int, *, rs485: bool = False) -> None:
        self.port = port
        self.baudrate = baudrate
        self.rs485 = rs485
        self._serial: serial.Serial | None = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._expect = 0  # bytes of the answer now awaited (0: none known)
        self._flow = _Flow()

    @property
    def is_open(self) -> bool:
        return self._serial is not None

    async def open(
        self, on_bytes: Callable[[bytes, float], None], on_lost: Callable[[Exception], None]
    ) -> None:
        """Open the port and start delivering received bytes to ``on_bytes(data, at)`` in
        the loop; ``at`` is when they came in (``time.monotonic()``, the loop's clock),
        which on a busy machine can be well before the loop gets round to them."""
        loop = asyncio.get_running_loop()
        if self.rs485 and "://" in self.port:
            # pyserial would accept the setting and silently ignore it.
            raise LinkError(f"cannot open {self.port}: kernel RS-485 mode needs a local "
                            "serial device, not a URL")
        try:
            ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.1,
                                        do_not_open=True)
            if "://" not in self.port:
                # One owner per line: a second program opening the same device gets a
                # clear "busy" error instead of both reading half of each answer.
                ser.exclusive = True
            if self.rs485:
                # Kernel RS-485 mode: the UART driver switches the transceiver's direction.
                ser.rs485_mode = serial.rs485.RS485Settings()
            # Opening a network URL may block on connect: keep it off the loop.
            await loop.run_in_executor(None, ser.open)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"cannot open {self.port}: {exc}") from None
        self._serial = ser
        # Each open has its own stop flag: a reader of an earlier open that is still
        # winding down can never touch this port.
        closing = self._closing = threading.Event()

        flow = self._flow = _Flow()  # this open's count of bytes on their way

        def take(data: bytes, at: float) -> None:
            flow.taken += len(data)
            on_bytes(data, at)

        def reader() -> None:
            tighten_timers(BUS_NICE)
            while not closing.is_set():
                try:
                    data = self._read_answer(ser, flow)
                except Exception as exc:  # any failure of the device means it is gone
                    if not closing.is_set():
                        loop.call_soon_threadsafe(self._lost, ser, on_lost, exc)
                    return
                if data and not closing.is_set():
                    flow.handed += len(data)
                    loop.call_soon_threadsafe(take, data, time.monotonic())
                flow.in_hand = 0

        self._thread = threading.Thread(target=reader, name=f"serial {self.port}", daemon=True)
        self._thread.start()

    def _read_answer(self, ser: serial.Serial, flow: _Flow) -> bytes:
        """The next bytes from the line: a whole answer when its length is known.

        The answer's bytes cannot come faster than the wire, so rather than waking up
        (and taking the GIL from busy front ends) per byte, sleep until the rest could
        all be in and take it in one piece.  What came in a burst counts as in (a late
        sender catches up at once); when nothing more comes in the time one more byte
        would take, the answer was shorter (an error frame): hand over what is here.
        """
        data = ser.read(max(1, ser.in_waiting))
        flow.in_hand = len(data)
        expect, self._expect = self._expect, 0
        while data and len(data) < expect:
            time.sleep(max(expect - len(data) - ser.in_waiting, 1) * 10 / self.baudrate)
            more = ser.read(ser.in_waiting)
            if not more:
                break
            data += more
            flow.in_hand = len(data)
        return data

    def pending(self) -> int:
        """Bytes that came in but have not reached ``on_bytes`` yet: in the driver's
        buffer, in the reader thread's hands, or handed to the loop and waiting their
        turn behind the very timer that asks.  A bus master whose timer fired late (a
        busy machine) looks here before it calls an answer missing."""
        ser = self._serial
        if ser is None:
            return 0
        flow = self._flow
        unseen = flow.in_hand + max(0, flow.handed - flow.taken)
        try:
            return int(ser.in_waiting) + unseen
        except (serial.SerialException, OSError, ValueError, TypeError):
            return unseen

    def _lost(self, ser: serial.Serial, on_lost: Callable[[Exception], None],
              exc: Exception) -> None:
        if self._serial is not ser:
            return  # an earlier open's reader: that port is closed already
        self.close()
        on_lost(exc)

    def write(self, data: bytes, expect: int = 0) -> None:
        """Send ``data``; ``expect`` is the length of the answer, when known."""
        self._expect = expect
        if self._serial is None:
            raise LinkError(f"{self.port} is not open")
        try:
            self._serial.write(data)
        except (serial.SerialException, OSError) as exc:
            raise LinkError(f"writing to {self.port}: {exc}") from None

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
        ser, self._serial = self._serial, None
        if ser is None:
            return
        self._closing.set()
        with contextlib.suppress(Exception):
            ser.cancel_read()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(1.0)
        with contextlib.suppress(Exception):
            ser.close()
