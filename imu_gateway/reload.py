"""A new config against the running one: what changed, and what a reload does about it
(docs/configuration.md, "Changing the config while running").

Sans-IO: ``diff_configs`` works on two ``GatewayConfig`` values alone, so the plan is
tested on values (``tests/test_reload.py``); ``app.Gateway.reload`` carries it out.

The plan, by part:

- a bus equal to its old self (its settings and its sensors' bus settings) is left
  alone: its port stays open, its schedule, learned timeouts and counters go on;
- a bus that gained or lost a sensor, its own settings and its other sensors' bus
  settings the same, keeps running: only its schedule changes (the new sensor joins,
  the gone one leaves after its exchange in flight), its port stays open;
- a bus whose settings changed (or a kept sensor's bus settings) is restarted alone;
- a front end whose own section changed is restarted alone; one whose section is the
  same hears ``sensors_changed`` when the sensors did (Modbus TCP: its unit map;
  MQTT: discovery published and swept; Sparkplug: a rebirth; OPC UA: the sensors'
  nodes added and deleted), with its connections kept;
- the sections that are no front end's are applied by the reloader itself
  (``sections.py``): ``http``'s credentials and rules at once, its listen address
  after the answer to the request; the alarm journal's file; the capture's settings;
- what cannot change live (the gateway id; ``http`` or ``capture`` turned on or off)
  is named as "needs a restart".
"""

from __future__ import annotations

import asyncio
import inspect
import logging
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from pydantic import BaseModel

from .config import BusConfig, GatewayConfig, config_from_dict, fields, load_config
from .config.loading import ConfigSource, save_atomically, shown, with_secrets_kept
from .errors import ConfigError
from .sections import LiveSections

if TYPE_CHECKING:
    from .alarms import Transition
    from .bus.runner import BusThread
    from .capture import Captures
    from .journal import JournalFile
    from .supervise import Frontend


class Gateway(Protocol):
    """What a reload needs of ``app.Gateway`` (a protocol: the app imports this module)."""

    config: GatewayConfig
    source: ConfigSource | None
    buses: BusThread
    journal_file: JournalFile | None
    captures: Captures | None

    def adopt(self, config: GatewayConfig) -> None: ...

    def start_bus(self, config: BusConfig) -> None: ...

    def index_buses(self) -> None: ...

    def frontend(self, name: str) -> Frontend | None: ...

    async def replace_frontend(self, name: str) -> None: ...

    def alarm_journal(self, since: float | None = None) -> list[Transition]: ...

    def hand_over_within(self, ms: int) -> None: ...

log = logging.getLogger("imu_gateway")

SHUTDOWN_GRACE = 10.0  # seconds a bus stopped by a reload gets for its exchange in flight

#: Sensor settings that are not the bus's business (the cache's, the alarms', Modbus
#: TCP's): a change of one alone restarts no bus.
NOT_THE_BUS = frozenset({"unit_id", "raw_unit_id", "alarms", "stale_after_ms"})
#: The front ends a reload can restart, in the order they are started.
LIVE_FRONTENDS = ("modbus", "opcua", "mqtt")
#: Sections the reloader applies itself (``sections.py``).
LIVE_SECTIONS = ("http", "alarm_journal", "capture", "hand_over_ms")
#: Of these, those that only a restart turns on or off: the REST server answering the
#: request; the lines' frame rings, sized when their ports open.
ON_OFF_RESTART = ("http", "capture")
#: Sections that only a restart applies: the gateway id names every front end's topics
#: and nodes (docs/configuration.md).
RESTART_ONLY = ("gateway_id",)
#: Keys whose values are never shown in a diff: the secrets a message never echoes, and
#: ``http``'s lists of users and tokens, whose entries hold them.
SECRET_KEYS = fields.SECRET_KEYS | {"users", "tokens"}


@dataclass(frozen=True)
class Change:
    """One part that changed, and how, in words (``baudrate 9600→19200``)."""

    name: str
    details: tuple[str, ...]

    def describe(self) -> str:
        return f"{self.name} ({', '.join(self.details)})" if self.details else self.name


@dataclass(frozen=True)
class SensorMove:
    """A sensor added to or removed from a bus."""

    sensor: str
    bus: str


@dataclass(frozen=True)
class ConfigDiff:
    """What a reload from one config to another does."""

    buses_added: tuple[str, ...] = ()
    buses_removed: tuple[str, ...] = ()
    buses_changed: tuple[Change, ...] = ()  # their settings changed: restarted
    buses_unchanged: tuple[str, ...] = ()
    sensors_added: tuple[SensorMove, ...] = ()
    sensors_removed: tuple[SensorMove, ...] = ()
    sensors_changed: tuple[Change, ...] = ()  # any setting of a sensor kept
    frontends_changed: tuple[Change, ...] = ()  # their section changed: restarted
    frontends_unchanged: tuple[str, ...] = ()
    sections_changed: tuple[Change, ...] = ()  # applied by the reloader (LIVE_SECTIONS)
    needs_restart: tuple[Change, ...] = ()

    @property
    def empty(self) -> bool:
        return not (self.buses_added or self.buses_removed or self.buses_changed
                    or self.sensors_added or self.sensors_removed or self.sensors_changed
                    or self.frontends_changed or self.sections_changed
                    or self.needs_restart)

    @property
    def sensor_set_changed(self) -> bool:
        """Any sensor added, removed or changed: the front ends' maps change."""
        return bool(self.sensors_added or self.sensors_removed or self.sensors_changed)

    @property
    def buses_restarted(self) -> tuple[str, ...]:
        """The buses kept whose master is started anew: their own settings changed, or
        a kept sensor's bus settings (removed buses are stopped, added ones started)."""
        gone = set(self.buses_added) | set(self.buses_removed)
        return tuple(c.name for c in self.buses_changed if c.name not in gone)

    @property
    def buses_rescheduled(self) -> tuple[str, ...]:
        """The buses kept running that gained or lost a sensor: only their schedule
        changes (``BusRunner.change_sensors``)."""
        moved = dict.fromkeys(m.bus for m in (*self.sensors_added, *self.sensors_removed))
        other = {*self.buses_added, *self.buses_removed, *self.buses_restarted}
        return tuple(n for n in moved if n not in other)

    def summary(self) -> str:
        """The one log line: ``reload: +1 sensor (boom2 on line-a, its schedule only),
        line-b restarted (baudrate 9600→19200), unchanged: line-c, modbus``."""
        if self.empty:
            return "reload: no change"
        restarted = set(self.buses_restarted)
        rescheduled = set(self.buses_rescheduled)
        parts = [_count("+", self.sensors_added, restarted, rescheduled),
                 _count("-", self.sensors_removed, restarted, rescheduled)]
        parts += [f"bus {name} added" for name in self.buses_added]
        parts += [f"bus {name} removed" for name in self.buses_removed]
        parts += [f"{c.name} restarted ({', '.join(c.details)})" for c in self.buses_changed]
        parts += [f"sensor {c.describe()}" for c in self.sensors_changed]
        parts += [f"{c.name} restarted ({', '.join(c.details)})"
                  for c in self.frontends_changed]
        parts += [f"{c.name} applied ({', '.join(c.details)})" for c in self.sections_changed]
        parts += [f"needs a restart: {c.describe()}" for c in self.needs_restart]
        unchanged = [*self.buses_unchanged, *self.frontends_unchanged]
        if unchanged:
            parts.append(f"unchanged: {', '.join(unchanged)}")
        return "reload: " + ", ".join(p for p in parts if p)

    def to_json(self) -> dict[str, Any]:
        """The diff as the REST answer shows it (docs/rest.md)."""
        def changes(items: Iterable[Change]) -> list[dict[str, Any]]:
            return [{"name": c.name, "changes": list(c.details)} for c in items]

        def moves(items: Iterable[SensorMove]) -> list[dict[str, str]]:
            return [{"sensor": m.sensor, "bus": m.bus} for m in items]

        return {
            "summary": self.summary(),
            "buses": {"added": list(self.buses_added), "removed": list(self.buses_removed),
                      "changed": changes(self.buses_changed),
                      "restarted": list(self.buses_restarted),
                      "rescheduled": list(self.buses_rescheduled),
                      "unchanged": list(self.buses_unchanged)},
            "sensors": {"added": moves(self.sensors_added),
                        "removed": moves(self.sensors_removed),
                        "changed": changes(self.sensors_changed)},
            "frontends": {"changed": changes(self.frontends_changed),
                          "unchanged": list(self.frontends_unchanged)},
            "sections": {"changed": changes(self.sections_changed)},
            "needs_restart": changes(self.needs_restart),
        }


def _count(sign: str, moves: tuple[SensorMove, ...], restarted: set[str],
           rescheduled: set[str]) -> str:
    if not moves:
        return ""
    what = ", ".join(f"{m.sensor} on {m.bus}"
                     + (f", {m.bus} restarted" if m.bus in restarted else
                        ", its schedule only" if m.bus in rescheduled else "")
                     for m in moves)
    return f"{sign}{len(moves)} sensor{'s' if len(moves) != 1 else ''} ({what})"


def differences(old: Any, new: Any, prefix: str = "") -> list[str]:
    """What differs between two values, in words: ``baudrate 9600→19200``; a mapping
    or model key by key, a secret's values never shown."""
    if old == new:
        return []
    if isinstance(old, BaseModel) and isinstance(new, BaseModel):
        # (warnings off: capture.on_alarms can hold a list where its type says tuple, and
        # pydantic's warning would fail the request; the values are what is compared)
        old, new = old.model_dump(mode="json", warnings=False), \
            new.model_dump(mode="json", warnings=False)
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        found: list[str] = []
        for key in dict.fromkeys([*old, *new]):
            where = f"{prefix}{key}"
            if str(key) in SECRET_KEYS and old.get(key) != new.get(key):
                found.append(f"{where} changed")
            else:
                found += differences(old.get(key), new.get(key), f"{where}.")
        return found
    where, change = prefix.rstrip("."), f"{_shown(old)}→{_shown(new)}"
    return [f"{where} {change}" if where else change]  # (no where: a top-level value)


def _shown(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, list | tuple):
        return f"[{', '.join(_shown(v) for v in value)}]"
    return str(getattr(value, "value", value))


def _bus_view(bus: BusConfig) -> dict[str, Any]:
    """A bus as its master sees it: its settings and its sensors' bus settings."""
    view = bus.model_dump(exclude={"sensors"})
    view["sensors"] = [s.model_dump(exclude=set(NOT_THE_BUS)) for s in bus.sensors]
    return view


def _bus_changes(old: BusConfig, new: BusConfig) -> tuple[str, ...]:
    """What changed of a kept bus that restarts it (a sensor more or less is said
    apart, by ``SensorMove``)."""
    details = differences(old.model_dump(exclude={"sensors"}),
                          new.model_dump(exclude={"sensors"}))
    old_s = {s.name: s.model_dump(exclude=set(NOT_THE_BUS)) for s in old.sensors}
    new_s = {s.name: s.model_dump(exclude=set(NOT_THE_BUS)) for s in new.sensors}
    for name in old_s.keys() & new_s.keys():
        details += differences(old_s[name], new_s[name], f"{name}.")
    kept_old = [n for n in old_s if n in new_s]
    kept_new = [n for n in new_s if n in old_s]
    if kept_old != kept_new:
        details.append("sensor order")
    return tuple(details)


def _frontends(old: GatewayConfig, new: GatewayConfig
               ) -> tuple[list[Change], list[str], list[Change], list[Change]]:
    changed: list[Change] = []
    unchanged: list[str] = []
    sections: list[Change] = []
    restart: list[Change] = []
    for name in (*LIVE_FRONTENDS, *LIVE_SECTIONS, *RESTART_ONLY):
        before, after = getattr(old, name), getattr(new, name)
        if before == after:
            if before is not None and name in (*LIVE_FRONTENDS, "http"):
                unchanged.append(name)
            continue
        if before is None or after is None:
            details: tuple[str, ...] = ("turned on" if before is None else "turned off",)
        else:
            details = tuple(differences(before, after)) or ("changed",)
        on_off = before is None or after is None
        (changed if name in LIVE_FRONTENDS else
         sections if name in LIVE_SECTIONS and not (on_off and name in ON_OFF_RESTART)
         else restart).append(Change(name, details))
    return changed, unchanged, sections, restart


def diff_configs(old: GatewayConfig, new: GatewayConfig) -> ConfigDiff:
    """What a reload from ``old`` to ``new`` does (both valid)."""
    old_buses = {b.name: b for b in old.buses}
    new_buses = {b.name: b for b in new.buses}
    bus_of_old = {s.name: b.name for b, s in old.iter_sensors()}
    bus_of_new = {s.name: b.name for b, s in new.iter_sensors()}
    old_sensors = {s.name: s for _, s in old.iter_sensors()}
    new_sensors = {s.name: s for _, s in new.iter_sensors()}
    # a sensor moved to another bus leaves one and joins the other
    added = tuple(SensorMove(n, b) for n, b in bus_of_new.items() if bus_of_old.get(n) != b)
    removed = tuple(SensorMove(n, b) for n, b in bus_of_old.items() if bus_of_new.get(n) != b)
    changed_buses, unchanged_buses = [], []
    for name in new_buses.keys() & old_buses.keys():
        details = _bus_changes(old_buses[name], new_buses[name])
        if details:
            changed_buses.append(Change(name, details))
        elif _bus_view(old_buses[name]) == _bus_view(new_buses[name]):
            unchanged_buses.append(name)
    sensors_changed = tuple(
        Change(n, tuple(differences(old_sensors[n], new_sensors[n])))
        for n in new_sensors if n in old_sensors and old_sensors[n] != new_sensors[n])
    frontends, unchanged, sections, restart = _frontends(old, new)
    order = [b.name for b in new.buses]
    return ConfigDiff(
        buses_added=tuple(n for n in order if n not in old_buses),
        buses_removed=tuple(n for n in old_buses if n not in new_buses),
        buses_changed=tuple(sorted(changed_buses, key=lambda c: order.index(c.name))),
        buses_unchanged=tuple(n for n in order if n in unchanged_buses
                              and not any(m.bus == n for m in (*added, *removed))),
        sensors_added=added, sensors_removed=removed, sensors_changed=sensors_changed,
        frontends_changed=tuple(frontends), frontends_unchanged=tuple(unchanged),
        sections_changed=tuple(sections), needs_restart=tuple(restart))


# ------------------------------------------------------------ carrying it out


@dataclass(frozen=True)
class PutOutcome:
    """What a ``PUT /api/v1/config`` did."""

    diff: ConfigDiff
    applied: bool
    saved: bool
    note: str  # why it was not saved, or where it was
    after_answer: str | None = None  # what is applied once the answer is sent
    #: what does it (the REST route runs it after sending the answer)
    then: Callable[[], Awaitable[None]] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"applied": self.applied, "saved": self.saved, "note": self.note,
                "needs_restart": [c.describe() for c in self.diff.needs_restart],
                "after_answer": self.after_answer, "diff": self.diff.to_json()}


class Reloader:
    """Applies a new config to the running gateway, one reload at a time."""

    def __init__(self, gateway: Gateway) -> None:
        self.gateway = gateway
        self._lock = asyncio.Lock()
        self.sections = LiveSections(gateway)

    async def from_file(self) -> ConfigDiff | None:
        """``SIGHUP``: the config file read again; a broken one changes nothing and its
        problems are logged."""
        source = self.gateway.source
        if source is None or source.path is None:
            log.warning("reload: the gateway was not started from a config file; "
                        "nothing to read again")
            return None
        try:
            new = load_config(source.path)
            data = ConfigSource.read(source.path).data
        except (ConfigError, OSError) as exc:
            problems = exc.problems if isinstance(exc, ConfigError) else [str(exc)]
            log.error("reload refused, nothing changed: %s", "; ".join(problems))
            return None
        async with self._lock:
            diff = await self._apply(new)
            source.data = data
        await self.sections.move_http()  # (no answer to wait for)
        return diff

    def shown(self) -> Any:
        """The config as ``GET /api/v1/config`` shows it: as written, secrets hidden."""
        source = self.gateway.source
        data = source.data if source is not None else \
            self.gateway.config.model_dump(mode="json", exclude_none=True)
        return shown(data)

    async def put(self, data: Mapping[str, Any], dry_run: bool) -> PutOutcome:
        """A new config's data (unexpanded): checked (raises ``ConfigError``), then,
        unless ``dry_run``, applied and saved to the file."""
        source = self.gateway.source
        old = source.data if source is not None else {}
        data = with_secrets_kept(data, old)
        new = config_from_dict(data)
        if dry_run:
            return PutOutcome(diff_configs(self.gateway.config, new), False, False,
                              "a dry run: nothing applied, nothing saved")
        async with self._lock:
            diff = await self._apply(new)
            saved, note = await asyncio.to_thread(self._save, data)
            if source is not None:
                source.data = data
            else:
                self.gateway.source = ConfigSource(None, data)
        (log.info if saved else log.warning)("reload: %s", note)
        moving = self.sections.moving()
        if moving is None:
            return PutOutcome(diff, True, saved, note)
        return PutOutcome(diff, True, saved, note, after_answer=(
            f"applied after this answer: the REST server moves to {moving} (its event "
            "streams end: their clients reconnect there)"), then=self.sections.spawn_move)

    def _save(self, data: Any) -> tuple[bool, str]:
        source = self.gateway.source
        if source is None or source.path is None:
            return False, "not saved: the gateway was started without a config file " \
                "(applied live until the next restart)"
        try:
            save_atomically(source.path, data)
        except OSError as exc:
            return False, (f"not saved: {source.path}: {exc.strerror or exc} (applied "
                           "live until the next restart; make the file writable by the "
                           "gateway's user to save)")
        return True, f"saved to {source.path} (the previous one kept as " \
            f"{source.path.name}.bak)"

    async def _apply(self, new: GatewayConfig) -> ConfigDiff:
        """What can change live changes; the rest stays as it was, named in the log."""
        gateway = self.gateway
        old = gateway.config
        diff = diff_configs(old, new)
        if diff.empty:
            log.info("%s", diff.summary())
            return diff
        kept = {c.name: getattr(old, c.name) for c in diff.needs_restart}
        applied = new.model_copy(update=kept)
        for name in (*diff.buses_removed, *diff.buses_restarted):
            await gateway.buses.stop_one(name, SHUTDOWN_GRACE)
        # a sensor removed leaves its bus before the cache forgets it, one added
        # joins after the cache knows it
        await self._reschedule(diff, old, applied, kept_only=True)
        gateway.adopt(applied)  # the sensors' maps, the cache, history, alarms
        for bus in applied.buses:
            if bus.name in diff.buses_added or bus.name in diff.buses_restarted:
                gateway.start_bus(bus)
        await self._reschedule(diff, old, applied, kept_only=False)
        gateway.index_buses()
        await self.sections.apply((c.name for c in diff.sections_changed),
                                  diff.sensor_set_changed)
        await self._frontends(diff)
        log.info("%s", diff.summary())
        for change in diff.needs_restart:
            log.warning("reload: %s needs a restart (kept as it was until then)",
                        change.describe())
        return diff

    async def _reschedule(self, diff: ConfigDiff, old: GatewayConfig, new: GatewayConfig,
                          kept_only: bool) -> None:
        """The buses kept running that gained or lost a sensor get their new sensors
        (``kept_only``: the sensors they had and keep, the removed ones gone)."""
        before = {b.name: {s.name for s in b.sensors} for b in old.buses}
        for bus in new.buses:
            if bus.name in diff.buses_rescheduled:
                if kept_only:
                    bus = bus.model_copy(update={"sensors": [
                        s for s in bus.sensors if s.name in before[bus.name]]})
                await self.gateway.buses.runners[bus.name].change_sensors(
                    bus, SHUTDOWN_GRACE)

    async def _frontends(self, diff: ConfigDiff) -> None:
        """A front end whose section changed restarts; one whose sensors changed
        updates its map (Modbus TCP) or restarts."""
        gateway = self.gateway
        changed = {c.name for c in diff.frontends_changed}
        for name in ("modbus", "opcua", "mqtt", "sparkplug"):
            section = "mqtt" if name == "sparkplug" else name
            current = gateway.frontend(name)
            if section in changed:
                await gateway.replace_frontend(name)
            elif diff.sensor_set_changed and current is not None:
                if hasattr(current, "sensors_changed"):
                    done = current.sensors_changed()
                    if inspect.isawaitable(done):  # a front end may need its loop
                        await done
                else:
                    await gateway.replace_frontend(name)
