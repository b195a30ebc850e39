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


async def test_a_frame_waits_for_its_samples_and_is_registered_once_they_are_in() -> None:
    arrived = threading.Event()  # the link delivering the samples of the frames' exposures
    seen: list[int] = []
    loop = FrameLoop(
        FakeSource(3, 0.001), lambda f: f.index, [seen.append], lambda f: arrived.is_set(), 5.0
    )
    threading.Timer(0.1, arrived.set).start()
    t0 = time.monotonic()
    await loop.run()
    assert time.monotonic() - t0 >= 0.1  # nothing was registered before the samples came
    assert seen == [1, 2, 3]  # frames that became ready together are all registered, in order
    assert (loop.stats.dropped, loop.stats.timed_out) == (0, 0)


async def test_a_frame_whose_samples_never_come_is_registered_after_the_longest_wait() -> None:
    seen: list[int] = []
    loop = FrameLoop(FakeSource(4, 0.001), lambda f: f.index, [seen.append], lambda f: False, 0.03)
    await loop.run()
    assert seen[-1] == 4  # none lost to waiting: each went out at the wait's end
    assert loop.stats.timed_out == len(seen)
    assert loop.stats.processed + loop.stats.dropped == loop.stats.captured
    assert loop.stats.latency_ms(0.5) >= 30.0


async def test_a_slow_registration_still_drops_frames_that_waited_out() -> None:
    def slow(frame: Frame) -> int:
        time.sleep(0.02)
        return frame.index

    seen: list[int] = []
    loop = FrameLoop(FakeSource(60, 0.002), slow, [seen.append], lambda f: True, 0.01)
    await loop.run()
    assert loop.stats.dropped > 20  # a backlog is not kept past the wait
    assert seen == sorted(seen)
    assert seen[-1] == 60
