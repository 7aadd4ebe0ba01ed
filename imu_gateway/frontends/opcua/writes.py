"""The gateway's samples written into asyncua's address space, past its write path.

A sample written writes every value and status node of its sensor, about 25, whether
a client monitors them or not; which samples are written, and when, is ``Samples``'s
(the newest when a client looks; each one where an item takes every value).
Through asyncua's ``Server.write_attribute_value`` (three coroutines deep, and a
check of each value's type against the node's) that was a task per sample and
2.3-2.4 µs a node; here 1.7, and no task unless a node is monitored.
A sample with OPC UA on and nobody subscribed went from 84 to 52 µs (the cache's
publish included; ``docs/benchmarks.md``).

What asyncua's write does that matters is kept:

* a Bad StatusCode makes the value null (Part 4, 7.7.1);
* a value setter on the node gets the value instead;
* the node's data-change callbacks (its monitored items) get it, in order: at once,
  without a coroutine, where the item is the gateway's (``tell_now``,
  ``SampledItems.datachange_now``: nearly always), the rest awaited in a task after
  the sample before's (``tell``).

The type check is left out: the gateway made these nodes and writes each with the
Variant type of its DataType (``nodes.variant``); ``tests/frontends/opcua`` checks that
every one does.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Awaitable, Callable, Iterable
from typing import Any

from asyncua import ua

from ...cache import Snapshot
from .sampling import EveryValue

log = logging.getLogger("imu_gateway.opcua")

Callback = Callable[[int, ua.DataValue], Awaitable[None]]
#: A monitored item due a value: its node's callbacks (looked up when it is told, so an
#: item deleted meanwhile, or a node a reload retired, is told nothing), its handle.
Due = tuple[dict[int, Callback], int, ua.DataValue]
_VALUE = ua.AttributeIds.Value
_NULL = ua.Variant(None, ua.VariantType.Null)


class DirectWriter:
    """Writes of one server's address space (``aspace``: asyncua's ``AddressSpace``)."""

    def __init__(self, aspace: Any) -> None:
        self._nodes = aspace._nodes  # (its own dict of NodeData: read per write, so
        # nodes a reload added or removed are those written)

    def write(self, nodeid: ua.NodeId, value: ua.DataValue, due: list[Due]) -> None:
        """Set the node's value now; its monitored items' callbacks go into ``due``."""
        node = self._nodes.get(nodeid)
        attval = None if node is None else node.attributes.get(_VALUE)
        if attval is None:
            return  # (a node a reload has just removed)
        if value.StatusCode is not None and value.StatusCode.is_bad():
            value = dataclasses.replace(value, Value=_NULL)
        if attval.value_setter is not None:
            attval.value_setter(node, _VALUE, value)
        else:
            attval.value = value
            attval.value_callback = None
        callbacks = attval.datachange_callbacks
        for handle in callbacks:
            due.append((callbacks, handle, value))


def tell_now(due: list[Due]) -> list[Due]:
    """Tell the sample's items that need no coroutine (``SampledItems.datachange_now``:
    nearly all), in order; returns the rest, from the first that does, for ``tell``.
    One's failure is logged and the rest go on."""
    for n, (callbacks, handle, value) in enumerate(due):
        callback = callbacks.get(handle)
        if callback is None:
            continue  # (deleted since the value was written)
        now = getattr(getattr(callback, "__self__", None), "datachange_now", None)
        if now is None:
            return due[n:]
        try:
            if not now(handle, value):
                return due[n:]
        except Exception:
            log.exception("opcua: a monitored item's data change (handle %s)", handle)
    return []


async def tell(due: list[Due], after: asyncio.Task[None] | None = None) -> None:
    """The monitored items' callbacks of one sample, in order, those still there, once
    ``after`` (the sample before's) has ended; one's failure is logged and the rest go
    on (as asyncua's own write does)."""
    if after is not None:
        await asyncio.wait((after,))
    for callbacks, handle, value in due:
        callback = callbacks.get(handle)
        if callback is None:
            continue  # (deleted since the value was written)
        try:
            await callback(handle, value)
        except Exception:
            log.exception("opcua: a monitored item's data change (handle %s)", handle)


@dataclasses.dataclass(frozen=True, slots=True)
class Part:
    """Which of a sensor's nodes a write writes: ``nodes``, or (``inside`` False) all
    but those.  (A key: its writer keeps the nodes it picks out for it.)"""

    nodes: frozenset[ua.NodeId]
    inside: bool

    def takes(self, node: ua.NodeId) -> bool:
        return (node in self.nodes) == self.inside


#: which of a sensor's nodes a write writes (None: every one)
Which = Part | None


#: parts kept at most (two a sensor with an item taking every value, as a rule)
MAX_PARTS = 64
#: a sensor's value nodes, (field, node), and status nodes, (row, node)
Values = list[tuple[str, ua.NodeId]]
Status = list[tuple[Any, ua.NodeId]]


class SensorNodes:
    """Each sensor's value and status nodes (a reload changes them), and the part of
    them a write takes (``Part``: kept per part, so that a sample's write does not
    test each node)."""

    def __init__(self) -> None:
        self.values: dict[str, Values] = {}
        self.status: dict[str, Status] = {}
        self._parts: dict[tuple[str, Part], tuple[Values, Status]] = {}

    def add(self, name: str, values: Values, status: Status) -> None:
        self.values[name], self.status[name] = values, status
        self._parts.clear()  # (of nodes gone or rebuilt)

    def remove(self, name: str) -> Values:
        """The sensor's nodes forgotten; returns its value nodes."""
        self.status.pop(name, None)
        self._parts.clear()
        return self.values.pop(name, [])

    def pairs(self) -> list[tuple[str, ua.NodeId]]:
        """Each sensor's value and status nodes, (sensor, node)."""
        return [(name, node) for name, pairs in self.values.items() for _, node in pairs] + \
            [(name, node) for name, pairs in self.status.items() for _, node in pairs]

    def part(self, name: str, which: Which) -> tuple[Values, Status]:
        """The sensor's value and status nodes ``which`` takes."""
        if which is None:
            return self.values[name], self.status[name]
        part = self._parts.get((name, which))
        if part is None:
            if len(self._parts) >= MAX_PARTS:  # (clients that keep changing their items)
                self._parts.clear()
            part = self._parts[(name, which)] = (
                [pair for pair in self.values[name] if which.takes(pair[1])],
                [pair for pair in self.status[name] if which.takes(pair[1])])
        return part


class Samples:
    """The gateway's samples into the address space, each sensor's newest written when
    a client looks: before each request, publish and sampling tick (``flush``, which
    the server's ``catch_up`` calls after the cache's).  A sample in between is seen
    by nobody: a Read gives the value at the time it is served, and an item sampled
    every 100 ms takes the newest value at its tick.  So a 100 Hz sensor that SCADA
    clients read, or sample every 100 ms, is written ten times a second, not a
    hundred.

    Except the nodes a monitored item takes every value of (sampling interval 0,
    ``EveryValue``): each sample is written into those as it comes (what was held
    for them goes first), and into the sensor's other nodes when a client looks, as
    above.  A client that takes every pitch and roll has two nodes written a sample,
    not the sensor's 25.

    ``write(snap, which)`` writes a sample into its nodes (those ``which`` says, None:
    all) and returns its monitored items' callbacks; ``nodes()`` gives each sensor's
    nodes, (sensor, node) pairs (a reload changes them); ``fail`` is told of a sample
    a look could not write, and of a callback's task that failed."""

    def __init__(self, write: Callable[[Snapshot, Which], list[Due]], every: EveryValue,
                 nodes: Callable[[], Iterable[tuple[str, ua.NodeId]]],
                 fail: Callable[[BaseException], None]) -> None:
        self._write = write
        self._every = every
        self._nodes = nodes
        self._fail = fail
        # the newest sample not yet written into a sensor's nodes (of a sensor in
        # ``_each``: into those outside its every-value nodes)
        self._held: dict[str, Snapshot] = {}
        self._version = -1  # of ``every`` when ``_each`` was worked out
        # sensor -> its nodes an item takes every value of (only sensors with one)
        self._each: dict[str, Part] = {}
        self._telling: asyncio.Task[None] | None = None  # a sample's items still told

    def offer(self, snap: Snapshot) -> None:
        """A sample (or a status change) of ``snap.name``."""
        if self._every.version != self._version:
            self._refresh()
        every = self._each.get(snap.name)
        if every is not None:
            self._take(snap, every)
        self._held[snap.name] = snap  # (older: this one replaces it)

    def flush(self) -> None:
        """Write what is held: a client looks.  A sample that fails is the server's
        failure (``fail``), not the client's request's nor the publish's: the other
        sensors' are written all the same."""
        if self._every.version != self._version:
            self._refresh()
        held, self._held = self._held, {}
        for name, snap in held.items():
            self._take_guarded(snap, _outside(self._each.get(name)))

    def forget(self, name: str) -> None:
        """The sensor's nodes are gone (a reload): what was held for them is not
        written into nodes a later reload may build again."""
        self._held.pop(name, None)
        self._version = -1  # (its nodes may come back: worked out again)

    def _refresh(self) -> None:
        self._version = self._every.version
        watched = self._every.nodes()
        each: dict[str, set[ua.NodeId]] = {}
        for name, node in self._nodes():
            if node in watched:
                each.setdefault(name, set()).add(node)
        now = {name: Part(frozenset(nodes), inside=True) for name, nodes in each.items()}
        for name in now.keys() | self._each.keys():
            before = self._each.get(name)
            if now.get(name) != before and (snap := self._held.pop(name, None)) is not None:
                # (what was held goes first, into the nodes it is not in yet)
                self._take_guarded(snap, _outside(before))
        self._each = now

    def _take_guarded(self, snap: Snapshot, which: Which) -> None:
        try:
            self._take(snap, which)
        except Exception as exc:
            self._fail(exc)

    def _take(self, snap: Snapshot, which: Which) -> None:
        """A sample written into its nodes (``which``), its monitored items told."""
        due = self._write(snap, which)
        before = self._telling
        if due and (before is None or before.done()):
            due = tell_now(due)  # (nearly always all of them: no task)
        if due:  # (the rest, in order, after the sample before's)
            self._telling = task = asyncio.create_task(tell(due, before))
            task.add_done_callback(self._written)

    def _written(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            self._fail(task.exception())  # type: ignore[arg-type]


def _outside(every: Part | None) -> Which:
    """A sensor's nodes other than those taken every value of (None: all)."""
    return None if every is None else Part(every.nodes, inside=False)
