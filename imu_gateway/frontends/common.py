"""What every front end needs of the gateway; ``app.Gateway`` provides it."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol

from ..alarms import AlarmCounts, AlarmState, Transition
from ..cache import Cache, Snapshot
from ..commands import CommandResult
from ..config import GatewayConfig, SensorConfig
from ..derived import json_bytes as json_bytes  # (where the front ends have it from)
from ..errors import ErrorKind, RequestFailed
from ..history import History
from ..scanning import ScanJob, ScanRequest
from ..stats import BusStats, FrontendCounts, SensorStats, Trace

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

    # The alarms (docs/alarms.md).  A transition reaches a front end as the cache's
    # ``ALARM`` event (``cache.subscribe(…, kinds=ALL_EVENTS)``; ``Snapshot.alarm``).

    def alarm_states(self) -> list[AlarmState]:
        """Every alarm with its state: sensor by sensor in config order, each sensor's
        configured alarms in config order, then its ``communication`` alarm."""
        ...

    def alarm_journal(self, since: float | None = None) -> list[Transition]:
        """The journal's transitions (the last 1000) at or after ``since`` (epoch
        seconds; ``None``: all), oldest first."""
        ...

    def acknowledge(self, sensor: str, alarm: str, who: str) -> AlarmState:
        """Acknowledge as ``who`` (the front end checked the client's rights; ``who``
        says who it is: ``rest 10.0.0.5``); returns the state after.  Raises
        ``RequestFailed``: ``unknown_sensor``, ``unknown_alarm`` (404),
        ``nothing_to_acknowledge`` (409: the alarm is normal or acknowledged already)."""
        ...

    def alarm_counts(self) -> AlarmCounts:
        """Transitions per alarm since start, and the journal file's counters."""
        ...

    # Scan and traffic (docs/rest.md, "Traffic" and "Scan").

    async def watch_traffic(self, bus: str,
                            watcher: Callable[[Trace], None]) -> Callable[[], None]:
        """Tell ``watcher`` every exchange of ``bus``; returns what stops it.  Raises
        ``RequestFailed`` (``not_found``) for a bus it does not have."""
        ...

    def scan(self, request: ScanRequest) -> ScanJob:
        """A scan of a port, not started; its ``bus``: the one paused for it."""
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
