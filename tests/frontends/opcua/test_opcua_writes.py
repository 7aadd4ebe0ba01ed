"""A sample's monitored items told without a coroutine where they can be
(``writes.tell_now``), the rest in a task after the sample before's (``tell``), in
order either way."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest
from asyncua import ua

from imu_gateway.frontends.opcua.writes import Due, tell, tell_now

VALUE = ua.DataValue(ua.Variant(1.0, ua.VariantType.Double))


class Items:
    """A monitored-item service as ``tell_now`` sees one: ``datachange_now`` answers
    whether it took the change (``takes``), its coroutine takes any."""

    def __init__(self, heard: list[tuple[str, int]], takes: bool = True) -> None:
        self.heard, self.takes = heard, takes

    def datachange_now(self, handle: int, value: Any) -> bool:
        if handle == 99:
            raise RuntimeError("a broken item")
        if self.takes:
            self.heard.append(("now", handle))
        return self.takes

    async def datachange_callback(self, handle: int, value: Any) -> None:
        self.heard.append(("awaited", handle))


def due_of(*entries: tuple[Items, int]) -> list[Due]:
    return [({handle: items.datachange_callback}, handle, VALUE) for items, handle in entries]


@pytest.mark.anyio
async def test_items_are_told_now_up_to_the_first_that_must_be_awaited() -> None:
    heard: list[tuple[str, int]] = []
    quick, slow = Items(heard), Items(heard, takes=False)
    due = due_of((quick, 1), (quick, 99), (quick, 2), (slow, 3), (quick, 4))
    deleted: Due = ({}, 5, VALUE)  # (its item deleted since the value was written)
    rest = tell_now([deleted, *due])
    assert heard == [("now", 1), ("now", 2)]  # (99's failure logged, the rest go on)
    assert [handle for _, handle, _ in rest] == [3, 4]
    await tell(rest)
    assert heard == [("now", 1), ("now", 2), ("awaited", 3), ("awaited", 4)]


@pytest.mark.anyio
async def test_a_sample_is_told_after_the_one_before() -> None:
    heard: list[tuple[str, int]] = []
    items = Items(heard, takes=False)
    gate = asyncio.Event()

    async def held(handle: int, value: Any) -> None:
        await gate.wait()
        heard.append(("held", handle))

    before = asyncio.create_task(tell([({1: held}, 1, VALUE)]))
    after = asyncio.create_task(tell(due_of((items, 2)), before))
    await asyncio.sleep(0)
    await asyncio.sleep(0)
    assert heard == []
    gate.set()
    await after
    assert heard == [("held", 1), ("awaited", 2)]
