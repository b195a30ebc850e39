"""Fixtures shared by the link tests."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from tests.link.sim_bridge import SimBridge


@pytest.fixture
async def bridge() -> AsyncIterator[SimBridge]:
    """The firmware mirror stepped in real time behind a memory transport."""
    b = SimBridge()
    b.start()
    yield b
    await b.stop()
