"""``writes.Samples`` on its own: what it holds for a sensor whose nodes a reload
removed is forgotten, and a sample that fails to be written is the server's failure,
not the other sensors' nor the client's look."""

from __future__ import annotations

from asyncua import ua

from imu_gateway.cache import Cache, Snapshot
from imu_gateway.frontends.opcua.sampling import EveryValue
from imu_gateway.frontends.opcua.writes import Due, Samples
from imu_gateway.model import Angles, Reading


def _samples(broken: str | None = None) -> tuple[Samples, list[int], list[BaseException]]:
    written: list[int] = []
    failed: list[BaseException] = []

    def write(snap: Snapshot) -> list[Due]:
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
