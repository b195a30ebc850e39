"""Transport tests must not leave python-can reader threads or serial handler threads behind."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _threads(no_leftover_threads: None) -> None:
    """Every test here runs under the suite's thread check (tests/conftest.py)."""
