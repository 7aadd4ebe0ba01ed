"""The alarms' state model (imu_gateway/alarms.py, docs/alarms.md) in virtual time:
every transition of ISA-18.2's four states, the delays, hysteresis at its edges, the
latch, acknowledgement in each state, band alarms, the communication alarm, the
journal, and the journal's file (a real file; /dev/full for a full disk).

The expected states come from the table in docs/alarms.md, written out here."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path

import pytest

from imu_gateway.alarms import (
    COMMUNICATION,
    JOURNAL_SIZE,
    AlarmRow,
    Alarms,
    Evaluator,
    Severity,
    State,
    Transition,
)
from imu_gateway.errors import ErrorKind, RequestFailed
from imu_gateway.journal import JournalFile

N, AU, AA, RU = State.NORMAL, State.ACTIVE_UNACKED, State.ACTIVE_ACKED, State.RTN_UNACKED
WALL = 1_800_000_000.0  # the wall clock's epoch seconds at virtual time 0


def lean(**options: object) -> Evaluator:
    """The issue's example: above 5, hysteresis 0.5 (it clears at 4.5)."""
    row = AlarmRow("boom", "boom_lean", "tilt", **{"above": 5.0, "hysteresis": 0.5,
                                                   **options})  # type: ignore[arg-type]
    return Evaluator(row)


def feed(alarm: Evaluator, *samples: tuple[float, float | None]) -> list[Transition]:
    """(virtual time, value) pairs; the transitions they made."""
    made = []
    for at, value in samples:
        change = alarm.sample(value, at, WALL + at)
        if change is not None:
            made.append(change)
    return made


def moves(changes: list[Transition]) -> list[tuple[State, State]]:
    return [(c.from_state, c.to_state) for c in changes]


def refused(alarm: Evaluator) -> RequestFailed:
    with pytest.raises(RequestFailed) as caught:
        alarm.acknowledge("op", WALL)
    assert caught.value.kind is ErrorKind.NOTHING_TO_ACKNOWLEDGE
    assert caught.value.status == 409
    return caught.value


# ------------------------------------------------------------------ the state model


def test_raise_ack_clear_goes_normal_active_acked_normal() -> None:
    alarm = lean()
    [up] = feed(alarm, (0.0, 1.0), (1.0, 5.2))
    assert (up.from_state, up.to_state, up.value, up.limit) == (N, AU, 5.2, 5.0)
    assert up.at == WALL + 1.0 and up.severity is Severity.WARNING and up.by is None
    ack = alarm.acknowledge("alice", WALL + 2)
    assert (ack.from_state, ack.to_state, ack.by, ack.value) == (AU, AA, "alice", None)
    assert alarm.snapshot().value == 5.2  # the value that raised it stays shown
    [down] = feed(alarm, (3.0, 4.0))
    assert (down.from_state, down.to_state, down.value) == (AA, N, 4.0)
    state = alarm.snapshot()
    assert (state.state, state.active, state.acked, state.since) == (N, False, True, WALL + 3)


def test_raise_clear_ack_goes_through_returned_to_normal_unacknowledged() -> None:
    alarm = lean()
    assert moves(feed(alarm, (0.0, 6.0), (1.0, 4.0))) == [(N, AU), (AU, RU)]
    state = alarm.snapshot()
    assert (state.active, state.acked) == (False, False)
    ack = alarm.acknowledge("bob", WALL + 2)
    assert (ack.from_state, ack.to_state, ack.by) == (RU, N, "bob")


def test_returned_to_normal_unacknowledged_raised_again_is_active_unacknowledged() -> None:
    alarm = lean()
    assert moves(feed(alarm, (0.0, 6.0), (1.0, 4.0), (2.0, 6.0))) == \
        [(N, AU), (AU, RU), (RU, AU)]


def test_ack_in_each_state() -> None:
    normal = lean()
    error = refused(normal)
    assert "boom/boom_lean is normal" in str(error)
    acked = lean()
    feed(acked, (0.0, 9.0))
    acked.acknowledge("op", WALL)
    assert "acknowledged already" in str(refused(acked))
    unacked = lean()
    feed(unacked, (0.0, 9.0))
    assert unacked.acknowledge("op", WALL).to_state is AA
    returned = lean()
    feed(returned, (0.0, 9.0), (1.0, 0.0))
    assert returned.acknowledge("op", WALL).to_state is N
    refused(returned)  # and then it is normal


def test_a_missing_value_changes_nothing() -> None:
    alarm = lean(on_delay_s=1.0)
    assert feed(alarm, (0.0, 6.0), (0.5, None), (0.7, float("nan"))) == []
    assert moves(feed(alarm, (1.0, 6.0))) == [(N, AU)]  # the delay ran on
    assert feed(alarm, (2.0, None), (3.0, None)) == []
    assert alarm.snapshot().state is AU


# ------------------------------------------------------------------ limits


def test_hysteresis_at_its_edges() -> None:
    """Raised above 5 (strictly), cleared at 4.5 or lower."""
    alarm = lean()
    assert feed(alarm, (0.0, 5.0)) == []  # at the limit is not above it
    assert moves(feed(alarm, (1.0, 5.01))) == [(N, AU)]
    assert feed(alarm, (2.0, 4.99), (3.0, 4.51)) == []  # inside the hysteresis: active
    [down] = feed(alarm, (4.0, 4.5))
    assert (down.to_state, down.value, down.limit) == (RU, 4.5, 5.0)
    assert feed(alarm, (5.0, 4.9), (6.0, 5.0)) == []  # below the raise limit again: no
    assert moves(feed(alarm, (7.0, 5.001))) == [(RU, AU)]


def test_without_hysteresis_it_clears_at_the_limit() -> None:
    alarm = lean(hysteresis=0.0)
    assert moves(feed(alarm, (0.0, 5.1), (1.0, 5.0))) == [(N, AU), (AU, RU)]


def test_below_alarm_and_its_hysteresis() -> None:
    alarm = Evaluator(AlarmRow("s", "low", "accel_z", below=0.5, hysteresis=0.1))
    assert feed(alarm, (0.0, 0.5)) == []
    [up] = feed(alarm, (1.0, 0.49))
    assert (up.to_state, up.limit) == (AU, 0.5)
    assert feed(alarm, (2.0, 0.59)) == []
    assert moves(feed(alarm, (3.0, 0.6))) == [(AU, RU)]


def test_band_alarm_is_active_outside_the_band() -> None:
    alarm = Evaluator(AlarmRow("s", "band", "pitch", above=10.0, below=-10.0,
                               hysteresis=1.0, severity=Severity.CRITICAL))
    assert feed(alarm, (0.0, 0.0), (1.0, 10.0), (2.0, -10.0)) == []
    [high] = feed(alarm, (3.0, 10.5))
    assert (high.to_state, high.limit, high.severity) == (AU, 10.0, Severity.CRITICAL)
    alarm.acknowledge("op", WALL)
    assert feed(alarm, (4.0, 9.5)) == []  # within the hysteresis of the high end
    [back] = feed(alarm, (5.0, 9.0))
    assert (back.to_state, back.limit) == (N, 10.0)
    [low] = feed(alarm, (6.0, -10.5))
    assert (low.to_state, low.limit) == (AU, -10.0)
    assert feed(alarm, (7.0, -9.5)) == []
    assert moves(feed(alarm, (8.0, -9.0))) == [(AU, RU)]
    # straight from one side to the other: still active, no transition
    feed(alarm, (9.0, 20.0))
    assert feed(alarm, (10.0, -20.0)) == [] and alarm.snapshot().state is AU


# ------------------------------------------------------------------ delays


def test_on_delay_must_hold_and_restarts_when_the_value_returns() -> None:
    alarm = lean(on_delay_s=2.0)
    assert feed(alarm, (0.0, 6.0), (1.9, 6.0)) == []
    assert feed(alarm, (1.95, 4.0)) == []  # back within: the delay starts again
    assert feed(alarm, (2.0, 6.0), (3.99, 6.0)) == []
    [up] = feed(alarm, (4.0, 6.5))
    assert (up.to_state, up.value, up.at) == (AU, 6.5, WALL + 4.0)


def test_off_delay_must_hold_before_it_clears() -> None:
    alarm = lean(off_delay_s=1.0)
    feed(alarm, (0.0, 6.0))
    assert feed(alarm, (1.0, 4.0), (1.5, 4.0), (1.9, 6.0), (2.0, 4.0), (2.9, 4.0)) == []
    assert moves(feed(alarm, (3.0, 4.0))) == [(AU, RU)]


def test_a_delay_ignores_the_wall_clock() -> None:
    """The delays run on ``at`` (monotonic): a wall clock stepped back an hour changes
    only the records' times."""
    alarm = lean(on_delay_s=1.0)
    assert alarm.sample(6.0, 10.0, WALL) is None
    change = alarm.sample(6.0, 11.0, WALL - 3600)
    assert change is not None and change.at == WALL - 3600


# ------------------------------------------------------------------ latch


def test_latched_alarm_stays_active_until_acknowledged() -> None:
    alarm = lean(latch=True)
    assert moves(feed(alarm, (0.0, 6.0), (1.0, 0.0), (2.0, 0.0))) == [(N, AU)]
    state = alarm.snapshot()
    assert (state.state, state.active, state.latch) == (AU, True, True)
    assert feed(alarm, (3.0, 6.0)) == []  # it came back: still the same alarm
    feed(alarm, (4.0, 0.0))
    ack = alarm.acknowledge("op", WALL)
    assert (ack.from_state, ack.to_state) == (AU, N)  # the value is back: over


def test_latched_alarm_acknowledged_while_active_clears_as_any() -> None:
    alarm = lean(latch=True)
    feed(alarm, (0.0, 6.0))
    assert alarm.acknowledge("op", WALL).to_state is AA
    assert moves(feed(alarm, (1.0, 4.0))) == [(AA, N)]


# ------------------------------------------------------------------ the set of alarms


def rows() -> list[AlarmRow]:
    return [AlarmRow("boom", "boom_lean", "pitch", above=5.0),
            AlarmRow("boom", "shock", "accel_z", below=0.5, severity=Severity.INFO)]


def test_alarms_list_every_alarm_and_each_sensors_communication_alarm_last() -> None:
    alarms = Alarms(rows(), ["boom", "arm"])
    names = [(s.sensor, s.name, s.field) for s in alarms.states()]
    assert names == [("boom", "boom_lean", "pitch"), ("boom", "shock", "accel_z"),
                     ("boom", COMMUNICATION, None), ("arm", COMMUNICATION, None)]
    comm = alarms.states()[-1]
    assert (comm.severity, comm.state, comm.value, comm.since) == (Severity.CRITICAL, N,
                                                                  None, None)


def test_a_sample_moves_the_alarms_of_its_fields_and_the_journal_keeps_them() -> None:
    alarms = Alarms(rows(), ["boom"])
    made = alarms.sample("boom", {"pitch": 6.0, "accel_z": 0.2}, 0.0, WALL)
    assert [(c.alarm, c.to_state) for c in made] == [("boom_lean", AU), ("shock", AU)]
    assert alarms.sample("boom", {"roll": 90.0}, 1.0, WALL + 1) == []  # neither field
    alarms.acknowledge("boom", "shock", "op", WALL + 2)
    assert [c.alarm for c in alarms.since(None)] == ["boom_lean", "shock", "shock"]
    assert [c.to_state for c in alarms.since(WALL + 1)] == [AA]
    assert alarms.transitions["boom", "shock"] == 2
    assert alarms.transitions["boom", COMMUNICATION] == 0


def test_acknowledging_what_is_not_there_names_it() -> None:
    alarms = Alarms(rows(), ["boom"])
    with pytest.raises(RequestFailed) as sensor:
        alarms.acknowledge("nope", "boom_lean", "op", WALL)
    assert sensor.value.kind is ErrorKind.UNKNOWN_SENSOR and sensor.value.status == 404
    with pytest.raises(RequestFailed) as alarm:
        alarms.acknowledge("boom", "nope", "op", WALL)
    assert alarm.value.kind is ErrorKind.UNKNOWN_ALARM and alarm.value.status == 404
    assert "boom_lean, shock, communication" in str(alarm.value)


def test_communication_alarm_follows_the_status() -> None:
    alarms = Alarms([], ["boom"])
    assert alarms.communication("boom", True, 0.0, WALL) is None
    up = alarms.communication("boom", False, 1.0, WALL + 1)
    assert up is not None and (up.alarm, up.to_state, up.value, up.limit) == \
        (COMMUNICATION, AU, None, None)
    assert alarms.communication("boom", False, 2.0, WALL + 2) is None
    down = alarms.communication("boom", True, 3.0, WALL + 3)
    assert down is not None and down.to_state is RU


def test_the_journal_keeps_the_last_thousand() -> None:
    alarms = Alarms([AlarmRow("boom", "x", "pitch", above=0.0)], ["boom"])
    for i in range(JOURNAL_SIZE + 10):
        alarms.sample("boom", {"pitch": 1.0 if i % 2 == 0 else -1.0}, i, WALL + i)
    kept = alarms.since(None)
    assert len(kept) == JOURNAL_SIZE and kept[-1].at == WALL + JOURNAL_SIZE + 9
    assert kept[0].at == WALL + 10


def test_states_are_taken_up_from_the_journal() -> None:
    """At start each alarm takes up its latest recorded state: an alarm raised and not
    acknowledged before a restart still asks for its acknowledgement."""
    past = [Transition("boom", "boom_lean", WALL, N, AU, 6.0, 5.0, Severity.WARNING),
            Transition("boom", "shock", WALL, N, AU, 0.1, 0.5, Severity.INFO),
            Transition("boom", "shock", WALL + 1, AU, RU, 0.9, 0.5, Severity.INFO),
            Transition("gone", "old", WALL, N, AU, 1.0, 0.0, Severity.INFO)]
    alarms = Alarms(rows(), ["boom"], past)
    states = {s.name: s for s in alarms.states()}
    assert (states["boom_lean"].state, states["boom_lean"].value) == (AU, 6.0)
    assert (states["shock"].state, states["shock"].since) == (RU, WALL + 1)
    assert len(alarms.since(None)) == 4  # the journal shows what it read, all of it
    # the restored active alarm clears as any would
    [down] = alarms.sample("boom", {"pitch": 1.0}, 0.0, WALL + 5)
    assert (down.from_state, down.to_state) == (AU, RU)


# ------------------------------------------------------------------ the journal's file


def test_transitions_go_to_the_file_and_come_back(tmp_path: Path) -> None:
    path = tmp_path / "journal.jsonl"
    alarms = Alarms(rows(), ["boom"])
    file = JournalFile(str(path))
    for change in [*alarms.sample("boom", {"pitch": 6.0}, 0.0, WALL + 0.25),
                   alarms.acknowledge("boom", "boom_lean", "rest 10.0.0.5", WALL + 1)]:
        file.append(change)
    file.close()
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert lines[0] == {"sensor": "boom", "alarm": "boom_lean", "ts": "2027-01-15T08:00:00.250Z",
                        "from": "normal", "to": "active_unacked", "value": 6.0, "limit": 5.0,
                        "severity": "warning", "by": None}
    assert lines[1]["by"] == "rest 10.0.0.5" and lines[1]["to"] == "active_acked"
    with path.open("a") as out:
        out.write("not json\n{\"sensor\": 1}\n")
    back = JournalFile(str(path)).read()
    assert back == alarms.since(None) and file.written == 2 and file.errors == 0


def test_a_full_disk_is_one_warning_and_a_count(caplog: pytest.LogCaptureFixture) -> None:
    """/dev/full: every write fails with ENOSPC.  Nothing raises; one warning for the
    run of failures; the count says how many transitions were lost."""
    file = JournalFile("/dev/full")
    assert file.read() == []  # a device is never read (it would never end)
    change = Transition("boom", "x", WALL, N, AU, 1.0, 0.0, Severity.INFO)
    with caplog.at_level(logging.WARNING, "imu_gateway.alarms"):
        for _ in range(3):
            file.append(change)
        file.close()
    assert file.errors == 3 and file.written == 0
    warnings = [r for r in caplog.records if "cannot write" in r.getMessage()]
    assert len(warnings) == 1 and "No space left" in warnings[0].getMessage()


# ------------------------------------------------------------------ the cache's ALARM event


def test_alarm_events_reach_those_who_ask_in_order_after_the_reading() -> None:
    """An alarm raised while the listeners hear a reading reaches every listener after
    that reading; a listener that did not ask for ``ALARM`` events never gets one."""
    from imu_gateway.alarms import AlarmEvent
    from imu_gateway.cache import ALL_EVENTS, Cache, EventKind, Snapshot
    from imu_gateway.model import Angles, Reading

    cache = Cache([("boom", 1000.0)], clock=lambda: 0.0)
    alarms = Alarms([AlarmRow("boom", "boom_lean", "pitch", above=5.0)], ["boom"])
    heard: dict[str, list[EventKind]] = {"first": [], "later": [], "plain": []}

    def evaluate(kind: EventKind, snap: Snapshot) -> None:  # as the gateway does
        if kind is EventKind.READING and snap.reading and snap.reading.angles:
            for change in alarms.sample("boom", {"pitch": snap.reading.angles.pitch}, 0, WALL):
                state = alarms.evaluator("boom", change.alarm).snapshot()
                cache.publish_alarm(AlarmEvent(change, state))

    def record(name: str) -> Callable[[EventKind, Snapshot], None]:
        def listener(kind: EventKind, snap: Snapshot) -> None:
            heard[name].append(kind)
            if kind is EventKind.ALARM:
                assert snap.alarm is not None and snap.alarm.state.state is AU
                assert snap.name == "boom" and snap.seq == 1
        return listener

    cache.subscribe(record("first"), kinds=ALL_EVENTS)
    cache.subscribe(evaluate)
    cache.subscribe(record("later"), kinds=ALL_EVENTS)
    cache.subscribe(record("plain"))
    cache.publish("boom", Reading(angles=Angles(9.0, 0.0, 0.0)))
    reading, status, alarm = EventKind.READING, EventKind.STATUS, EventKind.ALARM
    assert heard["first"] == heard["later"] == [reading, alarm, status]
    assert heard["plain"] == [reading, status]
