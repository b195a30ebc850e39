"""Transport tests must not leave python-can reader threads or serial handler threads behind."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

GRACE_S = 1.0


def _foreign_threads(before: set[threading.Thread]) -> list[threading.Thread]:
    """Threads started during the test, other than the event loop's executor workers."""
    return [
        t
        for t in threading.enumerate()
        if t not in before and t.is_alive() and not t.name.startswith(("asyncio_", "ThreadPool"))
    ]


@pytest.fixture(autouse=True)
def _no_leftover_threads() -> Iterator[None]:
    """Fail a test that leaves a thread running (after a short grace for joins)."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + GRACE_S
    while _foreign_threads(before) and time.monotonic() < deadline:
        time.sleep(0.01)
    leftover = _foreign_threads(before)
    assert not leftover, f"test left threads running: {leftover}"
