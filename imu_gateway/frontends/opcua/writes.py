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


class Samples:
    """The gateway's samples into the address space, each sensor's newest written when
    a client looks: before each request, publish and sampling tick (``flush``, which
    the server's ``catch_up`` calls after the cache's).  A sample in between is seen
    by nobody: a Read gives the value at the time it is served, and an item sampled
    every 100 ms takes the newest value at its tick.  So a 100 Hz sensor that SCADA
    clients read, or sample every 100 ms, is written ten times a second, not a
    hundred.

    Except where a monitored item takes every value (sampling interval 0,
    ``EveryValue``): each of that sensor's samples is written as it comes, and what
    was held for it goes first.

    ``write(snap)`` writes a sample into its nodes and returns its monitored items'
    callbacks; ``nodes()`` gives each sensor's nodes, (sensor, node) pairs (a reload
    changes them); ``fail`` is told of a sample a look could not write, and of a
    callback's task that failed."""

    def __init__(self, write: Callable[[Snapshot], list[Due]], every: EveryValue,
                 nodes: Callable[[], Iterable[tuple[str, ua.NodeId]]],
                 fail: Callable[[BaseException], None]) -> None:
        self._write = write
        self._every = every
        self._nodes = nodes
        self._fail = fail
        self._held: dict[str, Snapshot] = {}
        self._version = -1  # of ``every`` when ``_each`` was worked out
        self._each: frozenset[str] = frozenset()  # sensors with an item of every value
        self._telling: asyncio.Task[None] | None = None  # a sample's items still told

    def offer(self, snap: Snapshot) -> None:
        """A sample (or a status change) of ``snap.name``."""
        if self._every.version != self._version:
            self._refresh()
        if snap.name in self._each:
            self._held.pop(snap.name, None)  # (older: this one replaces it)
            self._take(snap)
        else:
            self._held[snap.name] = snap

    def flush(self) -> None:
        """Write what is held: a client looks.  A sample that fails is the server's
        failure (``fail``), not the client's request's nor the publish's: the other
        sensors' are written all the same."""
        if self._every.version != self._version:
            self._refresh()
        held, self._held = self._held, {}
        for snap in held.values():
            self._take_guarded(snap)

    def forget(self, name: str) -> None:
        """The sensor's nodes are gone (a reload): what was held for them is not
        written into nodes a later reload may build again."""
        self._held.pop(name, None)
        self._version = -1  # (its nodes may come back: worked out again)

    def _refresh(self) -> None:
        self._version = self._every.version
        watched = self._every.nodes()
        each = frozenset(name for name, node in self._nodes() if node in watched)
        for name in each - self._each:  # (now every value: the one held goes first)
            snap = self._held.pop(name, None)
            if snap is not None:
                self._take_guarded(snap)
        self._each = each

    def _take_guarded(self, snap: Snapshot) -> None:
        try:
            self._take(snap)
        except Exception as exc:
            self._fail(exc)

    def _take(self, snap: Snapshot) -> None:
        """A sample written into its nodes, its monitored items told."""
        due = self._write(snap)
        before = self._telling
        if due and (before is None or before.done()):
            due = tell_now(due)  # (nearly always all of them: no task)
        if due:  # (the rest, in order, after the sample before's)
            self._telling = task = asyncio.create_task(tell(due, before))
            task.add_done_callback(self._written)

    def _written(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            self._fail(task.exception())  # type: ignore[arg-type]
