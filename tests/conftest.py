"""Test hygiene (no asyncio task or timer may outlive its test; thread checks on request) and
the HIL rig fixtures."""

from __future__ import annotations

import asyncio
import compileall
import threading
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from tests.hil_rig import Rigs


PACKAGES = ("protocol", "firmware", "host", "hil_sim", "tests")


def pytest_sessionstart(session: pytest.Session) -> None:
    """Compile the project's modules once, first: where PYTHONDONTWRITEBYTECODE is set (as on
    our machines) each daemon, emulator and CLI process a test starts compiled them again."""
    root = Path(__file__).resolve().parents[1]
    for package in PACKAGES:
        if (root / package).is_dir():
            compileall.compile_dir(root / package, quiet=2)


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


THREAD_GRACE_S = 1.0  # for joins to finish


def _foreign_threads(before: set[threading.Thread]) -> list[threading.Thread]:
    """Threads started during the test, other than the event loop's executor workers."""
    return [
        t
        for t in threading.enumerate()
        if t not in before and t.is_alive() and not t.name.startswith(("asyncio_", "ThreadPool"))
    ]


@pytest.fixture
def no_leftover_threads() -> Iterator[None]:
    """Fail a test that leaves a thread running (after a short grace for joins)."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + THREAD_GRACE_S
    while _foreign_threads(before) and time.monotonic() < deadline:
        time.sleep(0.01)
    leftover = _foreign_threads(before)
    assert not leftover, f"test left threads running: {leftover}"


# The HIL rig fixtures (tests/hil_rig.py), imported when used: tests/test_hygiene.py runs a copy
# of this file where the tests package is not importable.
@pytest.fixture
def hil_rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rigs]:
    """Emulator + daemon rigs for one test; their processes end with it."""
    from tests.hil_rig import rigs_in

    with rigs_in(tmp_path_factory) as rigs:
        yield rigs


@pytest.fixture(scope="module")
def hil_rig_module(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rigs]:
    """Emulator + daemon rigs shared by a module's tests."""
    from tests.hil_rig import rigs_in

    with rigs_in(tmp_path_factory) as rigs:
        yield rigs
