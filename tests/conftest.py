"""Test hygiene shared by every test: no asyncio task or timer may outlive its test."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest


@pytest.fixture(autouse=True)
async def _no_leftover_tasks() -> AsyncIterator[None]:
    """Fail a test that leaves tasks running or timers scheduled on its event loop."""
    loop = asyncio.get_running_loop()
    before = asyncio.all_tasks(loop)
    yield
    await asyncio.sleep(0)
    me = asyncio.current_task()
    leftover = [t for t in asyncio.all_tasks(loop) - before if not t.done() and t is not me]
    timers = [h for h in getattr(loop, "_scheduled", []) if not h.cancelled()]
    for task in leftover:
        task.cancel()
    assert not leftover, f"test left tasks running: {leftover}"
    assert not timers, f"test left timers scheduled: {timers}"
