"""Host monotonic time to wall-clock time, for outputs read on other machines."""

from __future__ import annotations

import time


def monotonic_to_unix_ns(t_mono_ns: int) -> int:
    """The realtime (UTC) instant of a host monotonic one, read between two monotonic readings."""
    before = time.monotonic_ns()
    realtime = time.time_ns()
    after = time.monotonic_ns()
    return t_mono_ns - (before + after) // 2 + realtime
