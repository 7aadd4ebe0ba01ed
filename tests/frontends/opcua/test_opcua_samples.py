"""``writes.Samples`` on its own: what it holds for a sensor whose nodes a reload
removed is forgotten, a sample that fails to be written is the server's failure,
not the other sensors' nor the client's look, and a node an item takes every value of
gets each sample at once while the sensor's other nodes get the newest when a client
looks."""

from __future__ import annotations

from asyncua import ua

from imu_gateway.cache import Cache, Snapshot
from imu_gateway.frontends.opcua.sampling import EveryValue
from imu_gateway.frontends.opcua.writes import Due, Samples, Which
from imu_gateway.model import Angles, Reading


def _samples(broken: str | None = None) -> tuple[Samples, list[int], list[BaseException]]:
    written: list[int] = []
    failed: list[BaseException] = []

    def write(snap: Snapshot, which: Which) -> list[Due]:
        if snap.name == broken:
            raise ValueError(f"{snap.name}: a value its node refuses")
        written.append(snap.seq)
        return []

    def nodes() -> list[tuple[str, ua.NodeId]]:
        return [("a", ua.NodeId("a.pitch", 2)), ("b", ua.NodeId("b.pitch", 2))]

    return Samples(write, EveryValue(), nodes, failed.append), written, failed


def _cache() -> Cache:
    cache = Cache([("a", 1000), ("b", 1000)])
    for name in ("a", "b"):
        for pitch in (1.0, 2.0):
            cache.publish(name, Reading(angles=Angles(pitch, 0.0, 0.0)))
    return cache


def test_only_the_newest_is_written_when_a_client_looks() -> None:
    cache = Cache([("a", 1000), ("b", 1000)])
    samples, written, failed = _samples()
    offered = []
    for pitch in (1.0, 2.0, 3.0):
        cache.publish("a", Reading(angles=Angles(pitch, 0.0, 0.0)))
        offered.append(cache.snapshot("a").seq)
        samples.offer(cache.snapshot("a"))
    assert written == []
    samples.flush()
    assert written == [offered[-1]] and not failed
    samples.flush()
    assert written == [offered[-1]]  # (nothing new: nothing written)


def test_what_was_held_for_a_removed_sensor_is_not_written() -> None:
    cache = _cache()
    samples, written, _ = _samples()
    samples.offer(cache.snapshot("a"))
    samples.offer(cache.snapshot("b"))
    samples.forget("a")
    samples.flush()
    assert written == [cache.snapshot("b").seq]


def test_a_sample_that_fails_is_the_servers_failure_and_the_others_are_written() -> None:
    cache = _cache()
    samples, written, failed = _samples(broken="a")
    samples.offer(cache.snapshot("a"))
    samples.offer(cache.snapshot("b"))
    samples.flush()  # (raises nothing: the client's look goes on)
    assert written == [cache.snapshot("b").seq]
    assert [str(e) for e in failed] == ["a: a value its node refuses"]


PITCH, ROLL, OTHER = (ua.NodeId(f"a.{field}", 2) for field in ("pitch", "roll", "b"))


class _Watched(EveryValue):
    """The nodes taken every value of, as set here."""

    def __init__(self, *nodes: ua.NodeId) -> None:
        super().__init__()
        self.watched = set(nodes)

    def nodes(self) -> set[ua.NodeId]:
        return set(self.watched)


def _partial(every: EveryValue) -> tuple[Samples, list[tuple[int, set[ua.NodeId]]]]:
    """Samples of sensor a (nodes pitch and roll) and b, and what each write wrote:
    (seq, the nodes)."""
    written: list[tuple[int, set[ua.NodeId]]] = []
    failed: list[BaseException] = []
    pairs = [("a", PITCH), ("a", ROLL), ("b", OTHER)]

    def write(snap: Snapshot, which: Which) -> list[Due]:
        written.append((snap.seq, {node for name, node in pairs if name == snap.name
                                   and (which is None or which.takes(node))}))
        return []

    return Samples(write, every, lambda: pairs, failed.append), written


def test_a_node_taken_every_value_of_gets_each_sample_and_the_rest_the_newest() -> None:
    cache = Cache([("a", 1000), ("b", 1000)])
    samples, written = _partial(_Watched(PITCH))
    seqs = []
    for pitch in (1.0, 2.0):
        cache.publish("a", Reading(angles=Angles(pitch, 0.0, 0.0)))
        seqs.append(cache.snapshot("a").seq)
        samples.offer(cache.snapshot("a"))
    assert written == [(seqs[0], {PITCH}), (seqs[1], {PITCH})]
    samples.flush()
    assert written[2:] == [(seqs[1], {ROLL})]  # (the newest, into the other node only)
    samples.flush()
    assert len(written) == 3


def test_a_change_of_the_nodes_taken_every_value_of_writes_what_was_held_first() -> None:
    """What was held for a sensor goes, into the nodes it is not in yet, before a
    sample written under the new set: no node gets a sample twice or an older one
    after a newer."""
    cache = Cache([("a", 1000), ("b", 1000)])
    every = _Watched(PITCH)
    samples, written = _partial(every)
    cache.publish("a", Reading(angles=Angles(1.0, 0.0, 0.0)))
    held = cache.snapshot("a").seq
    samples.offer(cache.snapshot("a"))
    every.watched = {ROLL}
    every.changed()
    cache.publish("a", Reading(angles=Angles(2.0, 0.0, 0.0)))
    newer = cache.snapshot("a").seq
    samples.offer(cache.snapshot("a"))
    assert written == [(held, {PITCH}), (held, {ROLL}), (newer, {ROLL})]
    every.watched = set()  # (no item takes every value now)
    every.changed()
    samples.flush()  # (the newest goes into the nodes it is not in yet)
    assert written[3:] == [(newer, {PITCH})]
