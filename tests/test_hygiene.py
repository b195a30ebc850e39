"""The autouse fixture in tests/conftest.py really fails tests that leave tasks or timers behind.

Each case runs in a fresh pytest (pytester) with a copy of our conftest and our asyncio settings,
so a broken fixture shows up here as a test that unexpectedly passes.
"""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

CONFTEST = Path(__file__).resolve().parent / "conftest.py"
INI = """
[pytest]
asyncio_mode = auto
asyncio_default_fixture_loop_scope = function
"""
CASES = {
    "leaks_task": """
import asyncio

async def test_it():
    asyncio.get_running_loop().create_task(asyncio.sleep(3600))
""",
    "leaks_timer": """
import asyncio

async def test_it():
    asyncio.get_running_loop().call_later(3600, lambda: None)
""",
    "cleans_up": """
import asyncio

async def test_it():
    task = asyncio.get_running_loop().create_task(asyncio.sleep(3600))
    handle = asyncio.get_running_loop().call_later(3600, lambda: None)
    handle.cancel()
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
""",
}


def _run(pytester: pytest.Pytester, case: str) -> pytest.RunResult:
    """Run one case file beside a copy of our conftest, in a subprocess."""
    pytester.makeini(INI)
    pytester.makeconftest(CONFTEST.read_text(encoding="utf-8"))
    pytester.makepyfile(**{f"test_{case}": CASES[case]})
    # Without hypothesis' plugin, whose package pytest would assertion-rewrite on every import
    # (most of such a run's time; the cases use no hypothesis).
    return pytester.runpytest_subprocess(
        "-p", "no:cacheprovider", "-p", "no:hypothesispytest", "-q"
    )


def test_fixture_fails_a_test_leaking_a_task(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "leaks_task")
    result.assert_outcomes(passed=1, errors=1)
    result.stdout.fnmatch_lines(["*test left tasks running*"])


def test_fixture_fails_a_test_leaking_a_timer(pytester: pytest.Pytester) -> None:
    result = _run(pytester, "leaks_timer")
    result.assert_outcomes(passed=1, errors=1)
    result.stdout.fnmatch_lines(["*test left timers scheduled*"])


def test_fixture_passes_a_test_that_cleans_up(pytester: pytest.Pytester) -> None:
    _run(pytester, "cleans_up").assert_outcomes(passed=1)
