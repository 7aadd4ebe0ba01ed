"""Alarms: what a value means, evaluated on every sample in one place (docs/alarms.md).

Sans-IO: no clock, no thread, no file.  Each call takes the time as arguments: ``at``,
monotonic seconds, for the delays (a step of the wall clock must not shorten an
on-delay), and ``wall``, epoch seconds, for the records.  ``app.Gateway`` feeds it from
the cache and hands its transitions to the front ends and to the journal's file.

One ``AlarmRow`` per configured alarm (``config.schema.AlarmConfig.row``), plus the
built-in ``communication`` alarm of each sensor; one ``Evaluator`` per row, holding
ISA-18.2's states:

    NORMAL ──raise──► ACTIVE_UNACKED ──ack──► ACTIVE_ACKED
      ▲                   │  (latch: stays until ack)  │
      │                 clear                        clear
      └──────ack────── RTN_UNACKED ◄──┘              ──► NORMAL

Every change of state is a frozen ``Transition``: the journal keeps the last
``JOURNAL_SIZE`` of them.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from .errors import ErrorKind, RequestFailed, unknown_sensor

#: The built-in alarm of every sensor: active while it is stale or offline.
COMMUNICATION = "communication"
#: Transitions the journal keeps in memory (and reads back from its file at start).
JOURNAL_SIZE = 1000


class Severity(enum.Enum):
    """How urgent an alarm is (OPC UA's Severity: 200, 500, 800)."""

    INFO = "info"
    WARNING = "warning"
    CRITICAL = "critical"


class State(enum.Enum):
    """ISA-18.2's alarm states (docs/alarms.md has the table of transitions)."""

    NORMAL = "normal"
    ACTIVE_UNACKED = "active_unacked"
    ACTIVE_ACKED = "active_acked"
    RTN_UNACKED = "rtn_unacked"  # returned to normal, not yet acknowledged

    @property
    def active(self) -> bool:
        return self in (State.ACTIVE_UNACKED, State.ACTIVE_ACKED)

    @property
    def acked(self) -> bool:
        return self not in (State.ACTIVE_UNACKED, State.RTN_UNACKED)


@dataclass(frozen=True, slots=True)
class AlarmRow:
    """One alarm of one sensor, as configured.  ``field`` is ``None`` for the
    communication alarm (its condition is the sensor's status, not a value)."""

    sensor: str
    name: str
    field: str | None
    above: float | None = None
    below: float | None = None
    hysteresis: float = 0.0
    on_delay_s: float = 0.0
    off_delay_s: float = 0.0
    severity: Severity = Severity.WARNING
    latch: bool = False

    def beyond(self, value: float, active: bool) -> bool:
        """Whether ``value`` is in alarm.  Raised above ``above`` (strictly) or below
        ``below``; once active, it clears only at ``above - hysteresis`` or lower (at
        ``below + hysteresis`` or higher)."""
        h = self.hysteresis if active else 0.0
        if self.above is not None and (value > self.above - h if active else value > self.above):
            return True
        return self.below is not None and (value < self.below + h if active
                                           else value < self.below)

    def limit_for(self, value: float | None) -> float | None:
        """The limit a value is judged by: of a band, the nearer end."""
        if self.above is None or self.below is None or value is None:
            return self.above if self.above is not None else self.below
        return self.above if value >= (self.above + self.below) / 2 else self.below


def communication_row(sensor: str) -> AlarmRow:
    """The built-in alarm: critical, because while it is active none of the sensor's
    other alarms can be evaluated."""
    return AlarmRow(sensor, COMMUNICATION, None, severity=Severity.CRITICAL)


def iso(wall: float) -> str:
    """``2026-11-22T03:40:00.123Z`` (as the reading JSON's ``ts``)."""
    moment = datetime.fromtimestamp(wall, UTC)
    return moment.strftime("%Y-%m-%dT%H:%M:%S.") + f"{moment.microsecond // 1000:03d}Z"


def _wall_of(text: str) -> float:
    return datetime.fromisoformat(text).timestamp()


@dataclass(frozen=True, slots=True)
class Transition:
    """One change of an alarm's state: when, from what to what, the value that caused
    it and the limit it was judged by (``None`` for an acknowledgement, and for the
    communication alarm), and who acknowledged (``by``, only for an acknowledgement)."""

    sensor: str
    alarm: str
    at: float  # wall clock, epoch seconds
    from_state: State
    to_state: State
    value: float | None
    limit: float | None
    severity: Severity
    by: str | None = None

    def to_json(self) -> dict[str, Any]:
        """A journal line (docs/alarms.md, "The journal")."""
        return {"sensor": self.sensor, "alarm": self.alarm, "ts": iso(self.at),
                "from": self.from_state.value, "to": self.to_state.value,
                "value": self.value, "limit": self.limit, "severity": self.severity.value,
                "by": self.by}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Transition:
        """The inverse of ``to_json``; raises ``KeyError``, ``TypeError`` or
        ``ValueError`` for what is not one."""
        def number(key: str) -> float | None:
            value = data[key]
            return None if value is None else float(value)

        by = data["by"]
        return cls(str(data["sensor"]), str(data["alarm"]), _wall_of(str(data["ts"])),
                   State(data["from"]), State(data["to"]), number("value"), number("limit"),
                   Severity(data["severity"]), None if by is None else str(by))


@dataclass(frozen=True, slots=True)
class AlarmState:
    """An alarm as a client sees it at one moment.  ``value`` and ``limit`` are those
    of its latest transition (``None`` before the first); ``since`` is that
    transition's time (wall clock, epoch seconds)."""

    sensor: str
    name: str
    field: str | None
    severity: Severity
    state: State
    value: float | None
    limit: float | None
    since: float | None
    latch: bool

    @property
    def active(self) -> bool:
        return self.state.active

    @property
    def acked(self) -> bool:
        return self.state.acked

    def to_json(self) -> dict[str, Any]:
        return {"sensor": self.sensor, "alarm": self.name, "field": self.field,
                "severity": self.severity.value, "state": self.state.value,
                "active": self.active, "acked": self.acked, "value": self.value,
                "limit": self.limit, "since": None if self.since is None else iso(self.since),
                "latch": self.latch}


@dataclass(frozen=True, slots=True)
class AlarmEvent:
    """What the front ends get with the cache's ``ALARM`` event: the transition, and
    the alarm's state after it."""

    transition: Transition
    state: AlarmState

    def to_json(self) -> dict[str, Any]:
        """The state, with where it came from and who acknowledged (REST's stream)."""
        return {**self.state.to_json(), "from": self.transition.from_state.value,
                "by": self.transition.by}


class Evaluator:
    """One alarm's state, changed by samples (``sample``), by the sensor's status (the
    communication alarm: ``condition``) and by acknowledgement."""

    def __init__(self, row: AlarmRow) -> None:
        self.row = row
        self.state = State.NORMAL
        self.active = False  # the condition, after the delays (a latch may hold the state)
        self._pending: float | None = None  # when the condition began to differ (``at``)
        self._value: float | None = None
        self._limit: float | None = None
        self._since: float | None = None

    def sample(self, value: float | None, at: float, wall: float) -> Transition | None:
        """A sample's value of the row's field; ``None`` (the field absent) or NaN is no
        value and changes nothing."""
        if value is None or math.isnan(value):
            return None
        return self.condition(self.row.beyond(value, self.active), at, wall, value)

    def condition(self, beyond: bool, at: float, wall: float,
                  value: float | None = None) -> Transition | None:
        """The condition as it is now; it must hold for the row's on-delay (off-delay)
        before the alarm becomes active (clears).  A delay ends at the first call at
        or after its end."""
        if beyond == self.active:
            self._pending = None
            return None
        if self._pending is None:
            self._pending = at
        if at - self._pending < (self.row.on_delay_s if beyond else self.row.off_delay_s):
            return None
        self._pending = None
        self.active = beyond
        if beyond:  # raised (a latched alarm that cleared and comes back stays as it is)
            after = self.state if self.state.active else State.ACTIVE_UNACKED
        elif self.state is State.ACTIVE_ACKED:
            after = State.NORMAL
        else:  # cleared while unacknowledged: a latch holds it active
            after = self.state if self.row.latch else State.RTN_UNACKED
        if after is self.state:
            return None
        return self._move(after, wall, value, self.row.limit_for(value))

    def acknowledge(self, who: str, wall: float) -> Transition:
        """Acknowledge, as ``who``.  Raises ``RequestFailed`` (``nothing_to_acknowledge``)
        when the alarm is normal or acknowledged already."""
        if self.state.acked:
            what = "normal" if self.state is State.NORMAL else "acknowledged already"
            raise RequestFailed(ErrorKind.NOTHING_TO_ACKNOWLEDGE,
                                f"{self.row.sensor}/{self.row.name} is {what}: nothing to "
                                "acknowledge")
        after = State.ACTIVE_ACKED if self.active else State.NORMAL
        return self._move(after, wall, None, None, who)

    def restore(self, last: Transition) -> None:
        """Take up the state the journal last recorded (at start)."""
        self.state = last.to_state
        self.active = last.to_state.active
        self._value, self._limit, self._since = last.value, last.limit, last.at

    def _move(self, after: State, wall: float, value: float | None, limit: float | None,
              by: str | None = None) -> Transition:
        row = self.row
        change = Transition(row.sensor, row.name, wall, self.state, after, value, limit,
                            row.severity, by)
        self.state = after
        if by is None:  # (an acknowledgement keeps the value that raised the alarm)
            self._value, self._limit = value, limit
        self._since = wall
        return change

    def snapshot(self) -> AlarmState:
        row = self.row
        return AlarmState(row.sensor, row.name, row.field, row.severity, self.state,
                          self._value, self._limit, self._since, row.latch)


class Alarms:
    """Every alarm of every sensor, and the journal of their transitions.  Each call
    that changes a state returns the transitions it made, which are in the journal
    already."""

    def __init__(self, rows: Iterable[AlarmRow], sensors: Iterable[str],
                 journal: Iterable[Transition] = ()) -> None:
        """``rows``: the configured alarms; ``sensors``: every sensor's name (each gets
        its communication alarm, last); ``journal``: transitions read back, oldest
        first: each alarm takes up the state its latest one left it in."""
        self._by_sensor: dict[str, dict[str, Evaluator]] = {name: {} for name in sensors}
        self._fields: dict[str, tuple[tuple[str, Evaluator], ...]] = {}
        for row in rows:
            self._by_sensor[row.sensor][row.name] = Evaluator(row)
        for name, evaluators in self._by_sensor.items():
            evaluators[COMMUNICATION] = Evaluator(communication_row(name))
            self._fields[name] = tuple((e.row.field, e) for e in evaluators.values()
                                       if e.row.field is not None)
        self.journal: deque[Transition] = deque(journal, maxlen=JOURNAL_SIZE)
        for past in self.journal:
            found = self._by_sensor.get(past.sensor, {}).get(past.alarm)
            if found is not None:
                found.restore(past)
        self.transitions: dict[tuple[str, str], int] = dict.fromkeys(
            ((s, a) for s, alarms in self._by_sensor.items() for a in alarms), 0)

    def sample(self, sensor: str, values: Mapping[str, float], at: float,
               wall: float) -> list[Transition]:
        """A sample of ``sensor``: its values by field name (an absent one is no value)."""
        made = []
        for name, evaluator in self._fields[sensor]:
            change = evaluator.sample(values.get(name), at, wall)
            if change is not None:
                made.append(self._note(change))
        return made

    def communication(self, sensor: str, ok: bool, at: float,
                      wall: float) -> Transition | None:
        """The sensor's status: ``ok`` false while it is stale or offline."""
        change = self._by_sensor[sensor][COMMUNICATION].condition(not ok, at, wall)
        return None if change is None else self._note(change)

    def acknowledge(self, sensor: str, alarm: str, who: str, wall: float) -> Transition:
        """Raises ``RequestFailed``: ``unknown_sensor``, ``unknown_alarm``,
        ``nothing_to_acknowledge``."""
        return self._note(self.evaluator(sensor, alarm).acknowledge(who, wall))

    def evaluator(self, sensor: str, alarm: str) -> Evaluator:
        evaluators = self._by_sensor.get(sensor)
        if evaluators is None:
            raise unknown_sensor(sensor)
        found = evaluators.get(alarm)
        if found is None:
            raise RequestFailed(ErrorKind.UNKNOWN_ALARM,
                                f"{sensor} has no alarm {alarm!r} (its alarms: "
                                f"{', '.join(evaluators)})")
        return found

    def states(self) -> list[AlarmState]:
        """Every alarm, sensor by sensor in config order, each sensor's communication
        alarm last."""
        return [e.snapshot() for evaluators in self._by_sensor.values()
                for e in evaluators.values()]

    def since(self, wall: float | None) -> list[Transition]:
        """The journal's transitions at or after ``wall`` (all: ``None``), oldest first."""
        return list(self.journal) if wall is None else [t for t in self.journal if t.at >= wall]

    def _note(self, change: Transition) -> Transition:
        self.journal.append(change)
        self.transitions[change.sensor, change.alarm] += 1
        return change


@dataclass(frozen=True, slots=True)
class AlarmCounts:
    """The alarms' counters since start (Prometheus): transitions per (sensor, alarm),
    and the journal file's lines written and lost (0 without a file)."""

    transitions: Mapping[tuple[str, str], int]
    journal_written: int
    journal_errors: int
