"""A reload that adds a sensor to a running bus or removes one changes only that bus's
schedule (docs/bus-master.md, "A sensor added or removed by a reload"), in virtual
time (``virtual_line``): the other sensors' learned timeouts, counters and turns go
on; a removed sensor's exchange in flight ends first, and its stream is stopped."""

from __future__ import annotations

from typing import Any

import pytest
from support.virtual_line import VirtualLine, bus, sim

from imu_gateway.bus.events import Kind
from imu_gateway.commands import CommandResult
from imu_gateway.errors import ErrorKind
from imu_gateway.model import Series
from imu_gateway.protocol.exchanges import NativeAdapter


def sensor(name: str, address: int, **options: Any) -> dict[str, Any]:
    return {"name": name, "series": "AH", "address": address, "poll_hz": 0, **options}


def test_a_sensor_added_joins_the_schedule_and_the_others_go_on() -> None:
    line = VirtualLine(bus("native", [sensor("boom", 0)]),
                       [sim("native", "AH", 0), sim("native", "AH", 1, delay=0.010)])
    line.run(2.0)
    boom = line.schedule.sensors["boom"]
    learned, samples, transactions = boom.timer.srtt, boom.timer.samples, \
        boom.stats.transactions
    assert learned is not None and transactions > 100
    added = bus("native", [sensor("boom", 0), sensor("boom2", 1)]).sensors[1]
    line.schedule.add(added, line.now)
    line.run(2.0)
    assert line.schedule.sensors["boom"] is boom  # the same state, not a new one
    # its learned timing goes on (not from the first-answer timeout again)
    assert boom.timer.srtt == pytest.approx(learned) and boom.timer.samples > samples
    assert boom.stats.transactions > transactions  # counted on, not from zero
    boom2 = line.schedule.sensors["boom2"]
    assert boom2.online and boom2.timer.srtt is not None and boom2.timer.srtt > learned
    # a strict round robin of the two from then on
    late = [e.sensor for e in line.readings("boom") + line.readings("boom2")
            if e.at > line.now - 1.0]
    assert abs(late.count("boom") - late.count("boom2")) <= 1
    assert line.overlaps == 0 and line.collisions == 0


def test_a_removed_sensor_s_exchange_in_flight_ends_before_it_leaves() -> None:
    """Removed while its poll is on the line: the answer is waited for (nothing is
    written over it), its waiting command fails at once as offline, then it leaves
    and is never written to again."""
    sensors = [sim("native", "AH", 0), sim("native", "AH", 1, delay=0.030)]
    line = VirtualLine(bus("native", [sensor("boom", 0), sensor("slow", 1)]), sensors)
    line.run(1.0)
    schedule = line.schedule
    line.run(1.0, until=lambda: schedule.line.attempt is not None
             and schedule.line.attempt.job.sensor.name == "slow")
    waiting = line.command("slow", "read_settings")
    schedule.remove("slow", line.now)
    line.events += schedule.take_events()
    failed = line.result(waiting)
    assert failed is not None and isinstance(failed.outcome, CommandResult)
    assert failed.outcome.kind is ErrorKind.OFFLINE
    assert "slow was removed from the config" in str(failed.outcome.error)
    assert "slow" in schedule.sensors  # its poll is still on the line
    assert schedule.refusal("slow") is not None  # nothing new for it
    answers = len(line.readings("slow"))
    line.run(0.5, until=lambda: "slow" not in schedule.sensors)
    assert "slow" not in schedule.sensors
    writes = len(line.writes)
    line.run(1.0)
    poll = NativeAdapter().poll(Series.AH, 1).request
    assert not any(data == poll for _, data in line.writes[writes:])
    assert len(line.readings("slow")) <= answers + 1  # its last answer, no more
    assert len(line.readings("boom")) > 100 and line.overlaps == 0
    assert [s.name for s in schedule.sensors["boom"].line] == ["boom"]


def test_a_removed_streaming_sensor_is_stopped_first() -> None:
    """Its stream would meet the other sensors' exchanges once nobody places them in its
    pauses: it is told to stop, as at shutdown, then leaves."""
    sensors = [sim("native", "AH", 0), sim("native", "VG", 1)]
    line = VirtualLine(bus("native", [sensor("st", 0, stream_hz=20),
                                      {"name": "po", "series": "VG", "address": 1,
                                       "poll_hz": 0}]), sensors)
    line.run(3.0)
    assert line.schedule.sensors["st"].streaming and sensors[0].stream_interval
    line.schedule.remove("st", line.now)
    line.run(2.0)
    assert "st" not in line.schedule.sensors
    assert sensors[0].stream_interval == 0.0  # stopped
    polls = len(line.readings("po"))
    line.run(2.0)
    assert len(line.readings("po")) > polls + 100
    assert line.collisions == 0 and line.overlaps == 0


def test_a_removed_sensor_s_stream_set_up_is_finished_then_stopped() -> None:
    sensors = [sim("native", "AH", 0), sim("native", "AH", 1)]
    line = VirtualLine(bus("native", [sensor("st", 0, stream_hz=20), sensor("po", 1)]),
                       sensors)
    jobs = line.schedule.jobs
    line.run(1.0, until=lambda: jobs.current is not None and
             jobs.current.kind is Kind.STREAM_START and jobs.current.step == 1)
    line.schedule.remove("st", line.now)
    line.run(2.0)
    assert "st" not in line.schedule.sensors
    assert sensors[0].stream_interval == 0.0
    assert line.collisions == 0 and line.overlaps == 0
