"""What every front end needs of the gateway; ``app.Gateway`` provides it."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Protocol

from ..cache import Cache, Snapshot
from ..commands import CommandResult
from ..config import GatewayConfig, SensorConfig
from ..derived import json_bytes as json_bytes  # (where the front ends have it from)
from ..errors import ErrorKind, RequestFailed
from ..history import History
from ..stats import BusStats, FrontendCounts, SensorStats

if TYPE_CHECKING:  # (imported by the app only when capture is configured)
    from ..capture import Captures


class GatewayLike(Protocol):
    """What the front ends need of the gateway (``app.Gateway``)."""

    config: GatewayConfig
    cache: Cache
    sensors: dict[str, SensorConfig]
    history: History  # every sensor's last minutes, one for all front ends
    captures: Captures | None  # event capture (``capture:``; None: off)
    started: float  # time.monotonic() at start

    async def command(self, sensor: str, name: str,
                      args: Mapping[str, Any] | None = None) -> CommandResult: ...

    async def read(self, sensor: str, max_age_ms: float) -> Snapshot: ...

    async def passthrough(self, sensor: str, pdu: bytes) -> bytes: ...

    def stats(self) -> list[BusStats]:
        """Every bus master's stats."""
        ...

    def sensor_stats(self, name: str) -> SensorStats: ...

    def frontend_stats(self) -> dict[str, FrontendCounts]:
        """Each running front end's ``stats()``, by name (``modbus``, ``mqtt``, ``http``)."""
        ...


def peer_json(raw: bytes | str) -> Any:
    """JSON from a peer (a command's arguments), each object's keys given once.
    ``json.loads`` alone keeps the last of a repeated key, so that
    ``{"type": "absolute", "type": "relative"}`` would run as relative whatever the
    sender meant.  Raises ``RequestFailed`` (``bad_arguments``) naming the key, and
    ``ValueError`` or ``RecursionError`` for what is not JSON."""
    return json.loads(raw, object_pairs_hook=_once_each)


def _once_each(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    found: dict[str, Any] = {}
    for key, value in pairs:
        if key in found:
            raise RequestFailed(ErrorKind.BAD_ARGUMENTS,
                                f"the key {key!r} is given twice; give each key once")
        found[key] = value
    return found
