"""Each monitored item of a value sampled at its own sampling interval (OPC UA Part 4
5.12.1.2, docs/opcua.md "Monitored items' sampling").

asyncua 2.1 answers every CreateMonitoredItems with the subscription's publishing
interval as RevisedSamplingInterval (a Modify: the interval asked), and then ignores
it: each value written to a node becomes a notification of each of its items, queued
and encoded at the next publish.  A client told "sampled every 500 ms" got every
sample of a 100 Hz sensor, and that was most of the OPC UA server's CPU
(docs/benchmarks.md, "CPU per sample in the front ends").  Here:

* **The interval:** 0 is every sample (as before); a requested interval > 0 is
  rounded up to a multiple of ``SAMPLING_STEP_MS``, at most
  ``MAX_PUBLISHING_INTERVAL_MS``; a negative one (or NaN) is the subscription's
  publishing interval (at least ``SAMPLING_STEP_MS``).  The revised interval is
  answered in Create and Modify, and is the one used.  An item of events keeps
  asyncua's answer.
* **Sampling:** a write to the node of an item with an interval > 0 is only held, the
  newest replacing the one before (a change between two samples is not seen).  A
  ticker for each interval of the subscription hands each item's held value, if any,
  to the data-change path once per interval: the item's trigger and deadband, and
  its queue (queueSize, below), are asyncua's, as before (``_changed`` is asyncua's
  path with the notification made for less: ``encoding.py``).  A value written
  and then left (a sensor gone offline: its bad status) is sampled at the next tick.
  The initial value of a new item is reported at once (asyncua reads it then).
* **Writes:** a sensor whose nodes no item takes every value of (``EveryValue``)
  has only its newest sample written, when a client looks (``writes.Samples``):
  a Read, a tick and a publish each catch up first.
* **Queues** (Part 4 7.21, MonitoringParameters): for a value, a requested queueSize
  of 0 or 1 is a queue of 1, which keeps only the newest value; for events (alarms), 0
  is the server's default, ``MAX_QUEUE_SIZE``; never more than that.  asyncua makes 0
  its cap of 10 000 for both: a client that asked for the default and published
  slowly had every sample of a 100 Hz sensor queued and sent (memory held for it, and
  the CPU of encoding each).

The hook is asyncua's own class, one method each: :func:`sample_items` gives a new
subscription a :class:`SampledItems` (a ``MonitoredItemService``) before it has any
item, and that class overrides the public methods that create, modify and delete
items, the one that makes an item's common part (its queue), and the data-change
callback that each write calls.  The alternative, a
service of asyncua's ``SubscriptionService``, would mean replacing the server's own
``subscription_service``, which asyncua's session and server objects hold.
"""

from __future__ import annotations

import asyncio
import logging
import math
import weakref
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import ua
from asyncua.server.monitored_item_service import MonitoredItemService
from asyncua.server.subscription_service import SubscriptionService

from .encoding import notification

log = logging.getLogger("imu_gateway.opcua")


#: Sampling intervals other than 0 are whole multiples of this (ms): each distinct
#: interval of a subscription is a task of its own, which a client asking 0.001 ms, or
#: a thousand odd intervals, would keep busy; a 100 Hz sensor's sample comes every 10.
SAMPLING_STEP_MS = 10.0
#: A monitored item's queue holds at most this many values: 10 s of a 100 Hz sensor.
MAX_QUEUE_SIZE = 1000


def revised_queue(requested: int, events: bool) -> int:
    """An item's queue size (Part 4 7.21): a value's 0 and 1 are one value, the newest;
    an event item's 0 is ``MAX_QUEUE_SIZE``; none more than that."""
    return min(int(requested) or (MAX_QUEUE_SIZE if events else 1), MAX_QUEUE_SIZE)


def revised_interval(requested: float, publishing: float, most: float) -> float:
    """The sampling interval used for a value's item (ms): Part 4 5.12.1.2, with the
    server's fastest rate (0 is every sample) and steps (``SAMPLING_STEP_MS``)."""
    if not requested >= 0:  # negative (or NaN): the subscription's publishing interval
        return max(publishing, SAMPLING_STEP_MS) if publishing > 0 else 0.0
    if requested == 0:
        return 0.0
    step = SAMPLING_STEP_MS
    return min(step * math.ceil(requested / step), most)  # (never sooner than asked)


class EveryValue:
    """Which nodes a monitored item takes every value of (sampling interval 0), over
    every subscription of a server: the others' values need only be written when a
    client looks (``writes.Samples``).  ``version`` changes with any item created,
    modified or deleted; ``nodes`` is worked out again then, by whoever asks."""

    def __init__(self) -> None:
        self.version = 0
        self._services: weakref.WeakSet[SampledItems] = weakref.WeakSet()

    def add(self, service: SampledItems) -> None:
        self._services.add(service)
        self.version += 1

    def changed(self) -> None:
        self.version += 1

    def nodes(self) -> set[ua.NodeId]:
        return {node for service in self._services for node in service.every_value()}


class SampledItems(MonitoredItemService):  # type: ignore[misc]  # (asyncua is untyped)
    """asyncua's monitored items of one subscription, each value's sampled at its
    revised sampling interval."""

    def __init__(self, isub: Any, aspace: Any, most: float,
                 catch_up: Callable[[], None], every: EveryValue) -> None:
        super().__init__(isub, aspace)
        self.most = most  # ms: the longest interval given
        self._catch_up = catch_up  # (the cache's: a tick samples the newest value)
        self._every = every
        self._interval: dict[int, float] = {}  # callback handle -> ms, of items sampled
        self._held: dict[int, ua.DataValue] = {}  # handle -> newest value not sampled
        self._tickers: dict[float, tuple[set[int], asyncio.Task[None]]] = {}
        self._handing: set[asyncio.Task[None]] = set()  # values handed on by a Modify
        every.add(self)

    def every_value(self) -> list[ua.NodeId]:
        """The nodes of this subscription's items that take every value.  An item whose
        node a reload deleted (``live.retire``: it stays until its client deletes it,
        and hears nothing more) is not one: its handle is no longer the address
        space's, and a sensor rebuilt with the same NodeIds is not written sample by
        sample for it."""
        live = self.aspace._handle_to_attribute_map
        return [mdata.read_value_id.NodeId for mdata in self._monitored_items.values()
                if mdata.callback_handle is not None and
                mdata.callback_handle not in self._interval and mdata.callback_handle in live]

    async def create_monitored_items(self, params: Any) -> list[Any]:
        try:
            results: list[Any] = await super().create_monitored_items(params)
            for item, result in zip(params.ItemsToCreate or (), results, strict=True):
                mdata = self._monitored_items.get(result.MonitoredItemId)
                if result.StatusCode.is_good() and mdata is not None and \
                        mdata.callback_handle is not None:  # (None: an item of events)
                    result.RevisedSamplingInterval = self._revise(
                        mdata.callback_handle, item.RequestedParameters.SamplingInterval)
        finally:
            self._every.changed()
        return results

    def _make_monitored_item_common(self, params: Any) -> tuple[Any, Any]:
        result, mdata = super()._make_monitored_item_common(params)
        mdata.queue_size = result.RevisedQueueSize = revised_queue(
            params.RequestedParameters.QueueSize,
            params.ItemToMonitor.AttributeId == ua.AttributeIds.EventNotifier)
        return result, mdata

    def modify_monitored_items(self, params: Any) -> list[Any]:
        try:
            return self._modify(params)
        finally:
            self._every.changed()

    def _modify(self, params: Any) -> list[Any]:
        results = []
        for item in params.ItemsToModify or ():
            mdata = self._monitored_items.get(item.MonitoredItemId)
            if mdata is None:  # (asyncua's own answer to it raises a TypeError)
                results.append(ua.MonitoredItemModifyResult(StatusCode=ua.StatusCode(
                    ua.StatusCodes.BadMonitoredItemIdInvalid)))
                continue
            result = self._modify_monitored_item(item)  # the filter (and the queue, as asked)
            mdata.queue_size = result.RevisedQueueSize = revised_queue(
                item.RequestedParameters.QueueSize,
                mdata.read_value_id.AttributeId == ua.AttributeIds.EventNotifier)
            if mdata.callback_handle is not None:
                result.RevisedSamplingInterval = self._revise(
                    mdata.callback_handle, item.RequestedParameters.SamplingInterval)
            results.append(result)
        return results

    def delete_monitored_items(self, ids: list[int]) -> list[ua.StatusCode]:
        for mid in ids:
            mdata = self._monitored_items.get(mid)
            if mdata is not None and mdata.callback_handle is not None:
                self._held.pop(mdata.callback_handle, None)
                self._sample(mdata.callback_handle, 0.0)
        try:
            return list(super().delete_monitored_items(ids))
        finally:
            self._every.changed()

    async def datachange_callback(self, handle: int, value: Any, error: Any = None) -> None:
        # the one path of every write to a monitored node: kept short
        if error is not None:
            await super().datachange_callback(handle, value, error)
        elif handle in self._interval:
            self._held[handle] = value  # sampled at the item's next tick
        else:
            await self._changed(handle, value)

    async def _changed(self, handle: int, value: Any) -> None:
        """asyncua's data change of a value (``_noticed``), queued its way."""
        due = self._noticed(handle, value)
        if due is not None:
            await self.isub.enqueue_datachange_event(*due)

    def datachange_now(self, handle: int, value: Any) -> bool:
        """``datachange_callback`` of a value, without a coroutine: what nearly every
        sample of a monitored value is (``writes.tell_now``).  False, and nothing done,
        where asyncua's path would await: a subscription without a publishing loop
        publishes at its first change.  (It reads asyncua 2.1's private ``_task`` and
        ``_triggered_datachanges`` of the subscription; ``test_opcua_sampling`` sees
        every sample of a sampling-0 item arrive, in order, and no task made.)"""
        if handle in self._interval:
            self._held[handle] = value
            return True
        return self._queue_now(handle, value)

    def _queue_now(self, handle: int, value: Any) -> bool:
        """(``datachange_now``) A value of an item that takes every value, queued."""
        isub = self.isub
        if isub._task is None:
            return False
        due = self._noticed(handle, value)
        if due is not None:
            # asyncua's ``_enqueue_event``; its publish trigger does nothing while the
            # subscription's publishing loop runs
            mid, item, size = due
            queued = isub._triggered_datachanges.get(mid)
            if queued is None:
                isub._triggered_datachanges[mid] = [item]
            else:
                if size and len(queued) >= size:
                    queued.pop(0)
                queued.append(item)
        return True

    def _noticed(self, handle: int, value: Any) -> tuple[int, Any, int] | None:
        """asyncua's data change of a value, as its ``datachange_callback`` makes it
        (mode, trigger, deadband; the item's current value set): what to queue (its
        id, the notification, its queue's size), or None.  The notification is made
        with its value: asyncua's makes a default DataValue first
        (``encoding.notification``)."""
        mid = self._monitored_datachange[handle]
        mdata = self._monitored_items[mid]
        if mdata.mode == ua.MonitoringMode.Disabled:
            return None
        mdata.mvalue.set_current_datavalue(value)
        flt = mdata.filter
        if flt:
            passes = self._is_data_changed(mdata.mvalue, flt.Trigger) \
                and self._is_deadband_exceeded(mdata.mvalue, flt)
        else:
            passes = self._is_data_changed(mdata.mvalue, ua.DataChangeTrigger.StatusValue)
        if not passes:
            return None
        return mid, notification(mdata.client_handle, value), mdata.queue_size

    def _revise(self, handle: int, requested: float) -> float:
        interval = revised_interval(requested, self.isub.data.RevisedPublishingInterval,
                                    self.most)
        self._sample(handle, interval)
        return interval

    def _sample(self, handle: int, interval: float) -> None:
        """Sample the item of ``handle`` every ``interval`` ms (0: every value)."""
        before = self._interval.pop(handle, None)
        if before is not None:
            handles, task = self._tickers[before]
            handles.discard(handle)
            if not handles:
                task.cancel()
                del self._tickers[before]
        if interval > 0:
            self._interval[handle] = interval
            if interval not in self._tickers:
                handles = set()
                self._tickers[interval] = (handles, asyncio.create_task(
                    self._tick(interval, handles), name=f"opcua sampling {interval:g} ms"))
            self._tickers[interval][0].add(handle)
        elif (held := self._held.pop(handle, None)) is not None and \
                not self._queue_now(handle, held):
            # Now every value: the one held is not lost.  It was queued above, before
            # any newer one could be (a Modify cannot await asyncua's path); in a task
            # only for a subscription with no publishing loop yet.
            task = asyncio.create_task(self._hand_on(handle, held))
            self._handing.add(task)
            task.add_done_callback(self._handing.discard)

    async def _tick(self, interval: float, handles: set[int]) -> None:
        """Hand each item's held value on, once per ``interval`` ms: never sooner
        (a late tick does not bring the next one forward)."""
        loop = asyncio.get_running_loop()
        woke = loop.time()
        while True:
            await asyncio.sleep(max(0.0, woke + interval / 1000 - loop.time()))
            woke = loop.time()
            self._catch_up()
            for handle in list(handles):
                held = self._held.pop(handle, None)
                if held is not None:
                    await self._hand_on(handle, held)

    async def _hand_on(self, handle: int, value: Any) -> None:
        """The data-change path (trigger, deadband, queue) for a sampled value."""
        try:
            await self._changed(handle, value)
        except Exception:  # (asyncua's own writes log theirs too, and go on)
            log.exception("opcua: sampling monitored item %s", handle)


def sample_items(service: SubscriptionService, session_id: ua.NodeId, most: float,
                 catch_up: Callable[[], None], every: EveryValue) -> None:
    """Give the session's subscriptions that have asyncua's service a
    :class:`SampledItems` (called when one is made: it has no item yet); ``most``: the
    longest sampling interval, ms.  ``catch_up`` (the cache's, and the newest samples
    written) runs before each of the subscription's publishes and sampling ticks: the
    bus's turns wait for a reader.  ``every``: the server's register of items that
    take every value."""
    for sub in service.subscriptions.values():
        if sub.session_id == session_id and not isinstance(sub.monitored_item_srv, SampledItems):
            sub.monitored_item_srv = SampledItems(sub, service.aspace, most, catch_up, every)
            sub.publish_results = _caught_up(sub.publish_results, catch_up)


def _caught_up(publish: Callable[..., Awaitable[bool]],
               catch_up: Callable[[], None]) -> Callable[..., Awaitable[bool]]:
    """A subscription's ``publish_results`` (asyncua's publishing loop and publish
    requests call it through the instance), the cache caught up first."""

    async def publish_results(*args: Any, **kwargs: Any) -> bool:
        catch_up()
        return await publish(*args, **kwargs)

    return publish_results
