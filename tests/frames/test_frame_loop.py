"""The frame loop drops instead of queueing when starved, and ends cleanly."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from host.frames.loop import FrameLoop
from host.frames.sources import Frame


class FakeSource:
    """Delivers `count` tiny frames, `period_s` apart."""

    def __init__(self, count: int, period_s: float) -> None:
        self.count = count
        self.period_s = period_s
        self.sent = 0
        self.closed = False

    def read(self) -> Frame | None:
        if self.sent >= self.count:
            return None
        time.sleep(self.period_s)
        self.sent += 1
        return Frame(self.sent, np.zeros((2, 2, 3), np.uint8), time.monotonic_ns())

    def close(self) -> None:
        self.closed = True


async def test_slow_processing_drops_frames_instead_of_queueing() -> None:
    seen: list[int] = []

    def slow(frame: Frame) -> int:
        time.sleep(0.02)
        return frame.index

    loop = FrameLoop(FakeSource(60, 0.002), slow, [seen.append])
    await loop.run()
    st = loop.stats
    assert st.captured == 60
    assert st.dropped > 20
    assert st.processed == len(seen)
    assert st.processed + st.dropped == st.captured
    assert seen == sorted(seen)  # the newest frame wins; order is never reversed
    assert seen[-1] == 60  # the last frame is not lost


async def test_fast_processing_handles_every_frame() -> None:
    loop = FrameLoop(FakeSource(20, 0.005), lambda f: f.index)
    await loop.run()
    assert loop.stats.processed == 20
    assert loop.stats.dropped == 0
    assert loop.stats.latency_ms(0.5) < 1000.0


async def test_a_failing_frame_is_counted_and_the_loop_goes_on() -> None:
    def flaky(frame: Frame) -> int:
        if frame.index == 3:
            raise ValueError("bad frame")
        return frame.index

    loop = FrameLoop(FakeSource(6, 0.005), flaky)
    await loop.run()
    assert loop.stats.failed == 1
    assert loop.stats.processed == 5


async def test_stop_ends_the_loop_from_another_thread() -> None:
    loop = FrameLoop(FakeSource(10_000, 0.001), lambda f: f.index)
    threading.Timer(0.1, loop.stop).start()
    await loop.run()
    assert 0 < loop.stats.processed < 10_000


@pytest.mark.parametrize("limit", [1, 5])
async def test_max_frames_bounds_the_run(limit: int) -> None:
    loop = FrameLoop(FakeSource(100, 0.001), lambda f: f.index)
    await loop.run(max_frames=limit)
    assert loop.stats.processed == limit
