"""The sections of the config that are no front end's own restart, applied live by a
reload (docs/configuration.md, "Changing the config while running"):

- ``http``: its credentials and rules (tokens, users, roles, ``session_minutes``,
  ``allow_commands``, ``read_token_required``) from the next request on; its listen
  address once the answer to the request that changed it is sent (the REST server
  cannot move under its own answer).  An address that cannot be bound leaves the
  server where it was, and the config in force says so;
- ``alarm_journal``: the old file closed once what is queued for it is written, the
  new one written from the moment of the switch (nothing falls in between: both
  happen in one turn of the loop);
- ``capture``: the capture's new settings (``Captures.configure``);
- ``hand_over_ms``: from the bus thread's next turn.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Iterable, MutableMapping
from typing import TYPE_CHECKING, Protocol, cast

from .config import GatewayConfig, HttpConfig
from .config.loading import ConfigSource
from .journal import JournalFile

if TYPE_CHECKING:
    from .alarms import Transition
    from .capture import Captures
    from .supervise import Frontend

log = logging.getLogger("imu_gateway")


class _HttpServer(Protocol):
    """What a reload needs of the REST server (``frontends.rest.HttpServer``)."""

    config: HttpConfig

    def reconfigure(self, config: HttpConfig) -> None: ...

    async def move(self, config: HttpConfig) -> bool: ...


class Gateway(Protocol):
    """What these sections need of ``app.Gateway`` (part of ``reload.Gateway``)."""

    config: GatewayConfig
    source: ConfigSource | None
    journal_file: JournalFile | None
    captures: Captures | None

    def frontend(self, name: str) -> Frontend | None: ...

    def alarm_journal(self, since: float | None = None) -> list[Transition]: ...

    def hand_over_within(self, ms: int) -> None: ...


class LiveSections:
    """Applies ``http``, ``alarm_journal``, ``capture`` and ``hand_over_ms`` (one per
    reloader)."""

    def __init__(self, gateway: Gateway) -> None:
        self.gateway = gateway
        self._move_to: HttpConfig | None = None  # the REST server's next address
        self._tasks: set[asyncio.Task[None]] = set()

    async def apply(self, changed: Iterable[str], sensors_changed: bool) -> None:
        """The sections ``changed``, from the config just adopted (a capture's rings
        follow the sensors too)."""
        names = set(changed)
        config = self.gateway.config
        if "alarm_journal" in names:
            await self._journal(config.alarm_journal)
        if "hand_over_ms" in names:
            self.gateway.hand_over_within(config.hand_over_ms)
            log.info("reload: the buses' turns are handed over within %d ms",
                     config.hand_over_ms)
        captures = self.gateway.captures
        if captures is not None and config.capture is not None \
                and ("capture" in names or sensors_changed):
            await captures.configure(config.capture, config)
        server = self._server()
        if "http" in names and server is not None and config.http is not None:
            server.reconfigure(config.http)
            if config.http.listen != server.config.listen:
                self._move_to = config.http

    def moving(self) -> str | None:
        """Where the REST server moves once the answer is sent (None: it stays)."""
        return None if self._move_to is None else str(self._move_to.listen)

    async def spawn_move(self) -> None:
        """(After the answer is sent; async, so that Starlette runs it on the loop.)  A
        task of its own: stopping the old server waits for its requests, the one that
        sent the answer included."""
        task = asyncio.get_running_loop().create_task(self.move_http(), name="http move")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def move_http(self) -> None:
        target, self._move_to = self._move_to, None
        server = self._server()
        if target is None or server is None:
            return
        before = server.config.listen
        if await server.move(target):
            log.info("reload: the REST server moved from %s to %s", before, target.listen)
            return
        # still where it was: the config in force (GET /api/v1/config) says so
        gateway = self.gateway
        kept = target.model_copy(update={"listen": before})
        gateway.config = gateway.config.model_copy(update={"http": kept})
        data = gateway.source.data if gateway.source is not None else None
        http = data.get("http") if isinstance(data, MutableMapping) else None
        if isinstance(http, MutableMapping):
            http["listen"] = str(before)
        log.error("reload: http.listen %s not applied; the config in force says %s (the "
                  "file saved says %s: a restart would try it)", target.listen, before,
                  target.listen)

    def _server(self) -> _HttpServer | None:
        server = self.gateway.frontend("http")
        return cast(_HttpServer, server) if hasattr(server, "move") else None

    async def _journal(self, path: str | None) -> None:
        """The old file closed (what is queued for it written first), the new one
        written from now on.  A new file that is missing or empty starts with the
        transitions kept in memory, so that the next start reads the alarms' states
        from it; one that has lines is appended to."""
        gateway = self.gateway
        old = gateway.journal_file
        new = JournalFile(path) if path else None
        if new is not None and await asyncio.to_thread(new.is_empty):
            for change in gateway.alarm_journal(None):  # (no await from here to the switch)
                new.append(change)
        gateway.journal_file = new
        if old is not None:
            await asyncio.to_thread(old.close)
            if new is not None:
                new.follow(old)
        log.info("reload: the alarm journal is %s (was %s)",
                 path or "off", old.path if old is not None else "off")
