"""The gateway's samples written into asyncua's address space, past its write path.

A sample writes every value and status node of its sensor, about 25, whether a client
monitors them or not.  Through asyncua's ``Server.write_attribute_value`` (three
coroutines deep, and a check of each value's type against the node's) that was a task
per sample and 2.3-2.4 µs a node; here 1.7, and no task unless a node is monitored.
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
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import ua

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
