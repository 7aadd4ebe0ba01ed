"""Shared by every test: async tests (``@pytest.mark.anyio``) run on asyncio, the
gateway's own event loop, and on nothing else."""

from __future__ import annotations

import pytest


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The long tests (marked ``slow``) first, the rest in their order: with the suite in
    two workers (scripts/test), a long file that started last would run alone at the
    end while the other worker idles."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
