"""The pseudo-terminal's late hand-over: the rig's doing, not the master's.

A pty hands the master's bytes to the simulator in a kernel worker of normal priority.
Beside CPU burners that worker waits its turn, and a request the gateway wrote in its
place next to a stream was heard 23 and 47 ms later, on the stream's next frame: a
collision the soak blamed on the gateway.  The simulator now times a canary byte
through a pty of its own (``WireWatch``), and what a request read while the canary is
late meets is counted apart, as what follows a hold of its CPU is.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from serial import Serial
from support.harness import run, until

from imu_gateway.model import Series, WireProtocol
from imu_gateway.protocol import native
from imu_gateway.protocol.exchanges import char_time
from imu_gateway.simulator import SimSensor, SimulatorThread, make_sensor, simulated
from imu_gateway.simulator.bus import LAGGED, BusStats, WireWatch, overdue
from imu_gateway.simulator.sensor import Outgoing


def test_a_late_canary_says_the_line_s_bytes_may_be_late() -> None:
    stats, notes = BusStats(), list[str]()
    watch = WireWatch(stats, notes.append)
    watch.sent_at = 10.0
    assert not watch.late(10.0 + LAGGED / 2)  # under way, on time so far
    # held longer: the line's bytes may be held in the same worker now
    assert watch.late(10.0 + LAGGED * 1.2)
    watch.arrived(10.030)
    assert stats.lags == 1
    assert stats.lagged_s == pytest.approx(0.030)
    assert notes == ["LAGGED: the pty handed bytes over 30 ms late"]
    assert watch.late(10.030 + LAGGED / 2)  # released with the canary, read after it
    assert not watch.late(10.030 + LAGGED * 1.2)  # no blanket excuse


def test_a_canary_on_time_is_no_excuse() -> None:
    stats, notes = BusStats(), list[str]()
    watch = WireWatch(stats, notes.append)
    watch.sent_at = 20.0
    watch.arrived(20.0 + LAGGED * 0.8)
    assert (stats.lags, notes) == (0, [])
    assert not watch.late(20.0 + LAGGED)
    watch.arrived(21.0)  # no canary under way: nothing to time
    assert stats.lags == 0


def test_the_canary_goes_through_a_pty_of_its_own() -> None:
    """On a running line the canary is sent and comes through, again and again; none
    of it reaches the line."""
    with simulated([make_sensor(WireProtocol.NATIVE, Series.AH)]) as sim, \
            Serial(sim.path, 9600, timeout=0.05) as port:
        sent: set[float] = set()

        def three_canaries() -> bool:
            at = sim.call(lambda: sim.bus._wire.sent_at).result(5)
            if at is not None:
                sent.add(at)
            return len(sent) >= 3

        run(lambda: until(three_canaries))
        assert port.read(16) == b""
        assert sim.bus.stats.requests_bytes == 0


@contextmanager
def pty_late(late: bool, *sensors: SimSensor) -> Iterator[tuple[SimulatorThread, Serial]]:
    """A line whose pty hands every request over late (as the canary tells), or none."""
    with simulated(sensors) as sim, Serial(sim.path, 9600, timeout=1) as port:
        sim.call(setattr, sim.bus._wire, "late", lambda now: late).result(5)
        yield sim, port


@pytest.mark.parametrize("late", [True, False])
def test_an_overlap_is_the_rig_s_only_when_the_request_was_handed_over_late(
        late: bool) -> None:
    with pty_late(late, make_sensor(WireProtocol.NATIVE, Series.AH)) as (sim, port):
        port.write(native.encode_request("read_all"))
        run(lambda: until(lambda: sim.bus.stats.requests_bytes > 0))
        port.write(native.encode_request("read_all"))  # over the answer on its way
        run(lambda: until(lambda: sim.bus.stats.overlaps >= 1))
        stats = sim.bus.stats
    assert stats.overlaps == 1
    assert stats.masters_overlaps == (0 if late else 1) or stats.holds > 0
    assert any("of a request the pty handed over late" in e for e in stats.events) == late


@pytest.mark.parametrize("late", [True, False])
def test_a_collision_of_answers_to_a_request_handed_over_late_is_the_rig_s(
        late: bool) -> None:
    """Two sensors answer the address query at once: the answers of a request the pty
    held carry the excuse to their collision."""
    with pty_late(late, make_sensor(WireProtocol.NATIVE, Series.AH, 1),
                  make_sensor(WireProtocol.NATIVE, Series.VG, 2)) as (sim, port):
        port.write(native.encode_request("read_address"))
        run(lambda: until(lambda: sim.bus.stats.collisions >= 1))
        stats = sim.bus.stats
    assert stats.collisions == 1
    assert stats.masters_collisions == (0 if late else 1) or stats.holds > 0


def test_an_answer_the_simulator_has_not_sent_when_a_punctual_one_would_be_over() -> None:
    """The master's retry meets an answer the simulator still holds: the simulator's
    doing if a punctual sensor would have sent it whole by then (a hold of its thread
    too short for ``HoldWatch``: in CI beside burners the answer due at .2166 had not
    gone at .2318, 7.4 ms past its last beat), the master's if the answer is on the wire
    or would still be."""
    frame = bytes(57)  # an AH's read_all answer: 4.95 ms at 115200 baud
    answer = Outgoing(frame, not_before=10.0, baud=115200, solicited=True, sender="AH@0")
    wire = len(frame) * char_time(115200)
    assert overdue([answer], tx_end=0.0, now=10.0 + wire + 0.001)
    assert not overdue([answer], tx_end=0.0, now=10.0 + wire / 2)  # it would be sending
    assert not overdue([answer], tx_end=0.0, now=9.999)  # not due yet
    assert not overdue([answer], tx_end=11.0, now=10.5)  # one on the wire now
    assert not overdue([], tx_end=0.0, now=10.5)
    later = Outgoing(frame, not_before=10.2, baud=115200, solicited=True, sender="AH@1")
    assert not overdue([answer, later], tx_end=0.0, now=10.1)  # the second still due
