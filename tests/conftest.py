"""Shared by every test: async tests (``@pytest.mark.anyio``) run on asyncio, the
gateway's own event loop, and on nothing else."""

from __future__ import annotations

import pytest


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"
