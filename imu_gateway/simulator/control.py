"""The simulator's control socket: commands from outside its process, one line each.

``imu-gateway simulate --control PATH`` listens on a Unix socket at ``PATH``; a client
(``imu-gateway simulate-control PATH …``, ``socat``, a test) sends a command per line
and gets one line back: ``ok``, or ``error: `` and what was wrong and how to say it
right.  The commands run on the simulator's own loop, between its handling of the
line's bytes, so they need no lock.  A bad command, a client that disconnects mid-line
or sends garbage, is answered (or dropped) alone: the simulator and its line go on.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import stat
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

from ..errors import GatewayError
from ..model import WireProtocol
from .motion import PITCH_LIMIT, ROLL_LIMIT
from .sensor import SimSensor

#: The longest command line taken; a longer one is refused and its connection closed.
MAX_LINE = 256
COMMANDS = ("lean ADDRESS PITCH ROLL, lean ADDRESS off, turn ADDRESS HEADING [RATE], "
            "turn ADDRESS off")
#: A turn's heading and rate (deg/s) are at most this far from zero.
TURN_LIMIT = 3600.0
OK = "ok"


class BadCommand(GatewayError, ValueError):
    """A command the simulator cannot carry out; its text is the answer's reason (a
    leaf of ``imu_gateway.errors``'s tree)."""


def _number(text: str, name: str, limit: float) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not -limit <= value <= limit:  # NaN (and so a word) fails this too
        raise BadCommand(f"{name} must be a number of degrees from {-limit:g} to {limit:g}, "
                         f"not {text!r}")
    return value


def _sensor(sensors: Sequence[SimSensor], text: str) -> SimSensor:
    """The sensor ``text`` names: ``ADDRESS``, or ``PROTOCOL:ADDRESS`` where a native
    and a Modbus sensor share the address."""
    protocol_name, _, number = text.rpartition(":")
    protocols = {p.name.lower(): p for p in WireProtocol}
    if not number.isdigit() or (protocol_name and protocol_name.lower() not in protocols):
        raise BadCommand(f"ADDRESS is a bus address such as 1, or native:1 or modbus:1, "
                         f"not {text!r}")
    found = [s for s in sensors if s.address == int(number)
             and (not protocol_name or s.protocol is protocols[protocol_name.lower()])]
    if not found:
        here = ", ".join(s.name for s in sensors)
        raise BadCommand(f"no sensor at address {text} on this line (it has {here})")
    if len(found) > 1:
        raise BadCommand(f"address {text} is {' and '.join(s.name for s in found)}: say "
                         f"native:{number} or modbus:{number}")
    return found[0]


def execute(sensors: Sequence[SimSensor], line: str, now: float | None = None) -> str:
    """Carry out one command line at ``now`` (the simulator's clock; by default
    ``time.monotonic()``, which it is); the answer line (without its newline)."""
    words = line.split()
    now = time.monotonic() if now is None else now
    try:
        match words:
            case ["lean", address, "off"]:
                _sensor(sensors, address).lean(None)
            case ["lean", address, pitch, roll]:
                sensor = _sensor(sensors, address)
                sensor.lean(_number(pitch, "PITCH", PITCH_LIMIT),
                            _number(roll, "ROLL", ROLL_LIMIT))
            case ["turn", address, "off"]:
                _sensor(sensors, address).turn(None)
            case ["turn", address, heading, *rate] if len(rate) <= 1:
                sensor = _sensor(sensors, address)
                sensor.turn(_number(heading, "HEADING", TURN_LIMIT),
                            _number(rate[0], "RATE", TURN_LIMIT) if rate else 0.0, now)
            case ["turn", *_]:
                raise BadCommand(f"turn takes ADDRESS HEADING [RATE] or ADDRESS off, not "
                                 f"{' '.join(words[1:])!r}")
            case []:
                raise BadCommand(f"an empty line; the commands are {COMMANDS}")
            case ["lean", *_]:
                raise BadCommand(f"lean takes ADDRESS PITCH ROLL or ADDRESS off, not "
                                 f"{' '.join(words[1:])!r}")
            case _:
                raise BadCommand(f"unknown command {line.strip()[:40]!r}; the commands are "
                                 f"{COMMANDS}")
    except BadCommand as exc:
        return f"error: {exc}"
    return OK


@dataclass(frozen=True, slots=True)
class ControlSocket:
    """A listening control socket; ``close()`` stops it and removes its path."""

    path: str
    server: asyncio.AbstractServer

    def close(self) -> None:
        self.server.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)


def _clear_stale(path: str) -> None:
    """Remove a socket a simulator that is gone left at ``path``.  Anything else there
    (a file, a live simulator's socket) is refused with ``OSError``: nothing is taken
    from anyone."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(mode):
        raise FileExistsError(f"{path} exists and is not a socket; not replacing it")
    with socket.socket(socket.AF_UNIX) as probe:
        try:
            probe.connect(path)
        except ConnectionRefusedError:
            os.unlink(path)  # nobody listens: left over
            return
    raise FileExistsError(f"{path} is the control socket of a running simulator")


async def open_control(path: str, sensors: Sequence[SimSensor]) -> ControlSocket:
    """Listen for commands at ``path`` (a Unix socket).  ``OSError`` when it cannot: the
    path is taken, its folder is missing, or it is too long for a socket."""
    _clear_stale(path)

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await _converse(reader, writer, sensors)
        except (ConnectionError, OSError):
            pass  # the client went away: its business
        finally:
            writer.close()

    server = await asyncio.start_unix_server(serve, path, limit=MAX_LINE)
    return ControlSocket(path, server)


async def _converse(reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                    sensors: Sequence[SimSensor]) -> None:
    """Answer a client's lines until it closes its side (or sends one too long).  Only
    a whole line is a command: ``lean 1 5 12`` cut short at ``lean 1 5 1`` must not
    lean anything."""
    while True:
        try:
            raw = await reader.readline()
        except ValueError:  # over ``limit``: no line a command could be
            writer.write(f"error: a command is one line of at most {MAX_LINE} bytes\n"
                         .encode())
            await writer.drain()
            return
        if not raw.endswith(b"\n"):
            return  # closed, maybe mid-line: a command cut short is no command
        answer = execute(sensors, raw.decode("utf-8", errors="replace"))
        print(f"simulate: control: {raw.decode(errors='replace').strip()!r}: {answer}",
              file=sys.stderr, flush=True)
        writer.write(answer.encode() + b"\n")
        await writer.drain()


def send(path: str, command: str, timeout: float = 10.0) -> str:
    """Send one command line to a simulator's control socket; its answer line.
    ``OSError`` when the socket cannot be reached or does not answer in ``timeout``."""
    with socket.socket(socket.AF_UNIX) as sock:
        sock.settimeout(timeout)
        sock.connect(path)
        sock.sendall(command.encode() + b"\n")
        sock.shutdown(socket.SHUT_WR)
        answer = b""
        while not answer.endswith(b"\n") and (chunk := sock.recv(4096)):
            answer += chunk
    return answer.decode(errors="replace").strip()
