"""A bus master's port kept open: opened at start, reopened after a loss with a
back-off, and released for a scan of the line (``pause``).  Apart from ``master.py`` so
that each stays readable; it acts on its master's schedule and turns."""

from __future__ import annotations

import logging
import math
from typing import Protocol

from ..config import BusConfig
from ..errors import LinkError
from .link import SerialLink
from .reactor import Reactor
from .schedule import Schedule

log = logging.getLogger("imu_gateway.bus")

REOPEN_MIN, REOPEN_MAX = 0.5, 5.0  # seconds between tries to reopen a lost port


class Master(Protocol):
    """What the port's keeping needs of its ``BusMaster`` (a protocol: the master
    imports this module)."""

    name: str
    config: BusConfig
    link: SerialLink
    reactor: Reactor | None
    schedule: Schedule

    @property
    def done(self) -> bool: ...

    @property
    def port_open(self) -> bool: ...

    def now(self) -> float: ...

    def dispatch(self) -> None: ...

    def poke(self) -> None: ...

    def turn(self, drained: bool = False) -> None: ...

    def on_bytes(self, data: bytes, at: float) -> None: ...


class PortKeeper:
    """When the master's port is (re)opened, and what its loss or release does."""

    def __init__(self, master: Master) -> None:
        self.master = master
        self.reopen_at = math.inf  # the loop's turn to open it (inf: none asked)
        self._reopen_delay = REOPEN_MIN
        self._problem_logged = False
        self.paused = False  # released for a scan of the line

    def pause(self, reason: str | None) -> float:
        """Release the port for ``reason`` (a scan of the line uses it): the exchange in
        flight and every job waiting fail with it, and nothing goes out until
        ``pause(None)`` opens it again.  The sensors keep their state and counters.
        Returns when the line is quiet (``Line.quiet_at``): the answer to a request in
        flight may come until then, and whoever writes next must wait for it, as the
        bus would have (met on the wire, it garbles both; heard, it is a frame nobody
        asked for)."""
        m = self.master
        now = m.now()
        quiet = m.schedule.line.quiet_at(now)
        if m.done or (reason is not None) == self.paused:
            return quiet
        self.paused = reason is not None
        log.warning("bus %s: %s", m.name, reason or "polling resumed")
        self.reopen_at = math.inf if reason else now
        if reason:
            m.link.close()
            m.schedule.close(now, reason)
            m.dispatch()
        return quiet

    def open(self) -> None:
        m = self.master
        assert m.reactor is not None
        m.link.open(m.reactor, m.on_bytes, self.lost, self._opened)

    def _opened(self, error: LinkError | None) -> None:
        m = self.master
        if m.done or self.paused:  # (paused while it was opening)
            m.link.close()
            return
        if error is None:
            try:
                m.link.set_baudrate(m.schedule.baud)
            except LinkError as exc:
                m.link.close()
                error = exc
        if error is not None:
            if not self._problem_logged:
                log.warning("bus %s: %s; retrying", m.name, error)
                self._problem_logged = True
            m.schedule.lost(m.now(), str(error))
            m.dispatch()
            self.reopen_at = m.now() + self._reopen_delay
            self._reopen_delay = min(self._reopen_delay * 2, REOPEN_MAX)
            m.poke()  # a stop that came meanwhile finishes now
            return
        if self._problem_logged:
            log.warning("bus %s: port %s is back", m.name, m.config.port)
        else:
            log.info("bus %s: port %s open at %d baud", m.name, m.config.port,
                     m.schedule.baud)
        self._problem_logged = False
        self._reopen_delay = REOPEN_MIN
        m.schedule.open(m.now())
        m.turn()

    def lost(self, exc: Exception) -> None:
        """The port is gone (reported by the reader or by a failed write): once."""
        m = self.master
        if not m.port_open:
            return
        m.link.close()
        log.warning("bus %s: port %s lost (%s); reopening", m.name, m.config.port, exc)
        self._problem_logged = True
        m.schedule.lost(m.now(), str(exc))
        m.dispatch()
        self.reopen_at = m.now()
        m.poke()
