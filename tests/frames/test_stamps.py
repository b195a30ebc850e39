"""The exposure clock: a free-running camera's delivery stamps back on its steady frame clock."""

from __future__ import annotations

import numpy as np
import pytest

from hil_sim.camera import FrameClock
from host.control.cli_text import frames_text
from host.frames.sources import Frame
from host.frames.stamps import (
    EARLY_NS,
    MIN_FRAMES,
    ExposureClock,
    SteadyClockSource,
)

PERIOD_NS = 33_333_333.3 * (1 + 40e-6)  # a 30 fps sensor whose crystal is 40 ppm off the host's
DELAY_NS = 20e6
T0_NS = 5_000_000_000_000


def camera(
    n: int, seed: int = 1, drop: float = 0.0, stall: tuple[float, float] = (0.0, 0.0)
) -> tuple[list[float], list[int]]:
    """Exposures on the sensor's clock and their delivery stamps: delay + |N(0, 1 ms)|, a share
    `drop` of frames lost, a share stall[0] late by up to stall[1] ns more."""
    rng = np.random.default_rng(seed)
    delivery = FrameClock(delivery_s=DELAY_NS / 1e9, jitter_s=1e-3, seed=seed)
    exposures: list[float] = []
    stamps: list[int] = []
    k = 0
    for _ in range(n):
        k += 2 if rng.random() < drop else 1
        e = T0_NS + k * PERIOD_NS
        stamp = delivery.stamp_ns(round(e))
        if rng.random() < stall[0]:
            stamp += round(stall[1] * rng.random())
        exposures.append(e)
        stamps.append(max(stamp, stamps[-1] + 100_000) if stamps else stamp)  # in order
    return exposures, stamps


def placed(clock: ExposureClock, stamps: list[int]) -> list[int]:
    return [clock.place(s) for s in stamps]


def test_the_jitter_is_taken_out_and_the_mean_delay_kept() -> None:
    exposures, stamps = camera(1500, drop=0.03)
    clock = ExposureClock()
    out = np.asarray(placed(clock, stamps), np.float64)
    e = np.asarray(exposures)
    raw_err, err = (np.asarray(stamps) - e)[MIN_FRAMES:], (out - e)[MIN_FRAMES:]
    assert raw_err.std() > 0.5e6  # |N(0, 1 ms)|: 0.6 ms
    assert err.std() < 0.15e6  # the line: a sixth of it or less
    assert abs(err.mean() - raw_err.mean()) < 0.05e6  # the calibrated latency still applies
    assert clock.stats.restarts == 0
    # the slope of 300 stamps 0.6 ms apart is good to ~0.4 µs a period
    assert clock.stats.period_us == pytest.approx(PERIOD_NS / 1e3, abs=2.0)


def test_stamps_pass_through_until_the_line_is_known() -> None:
    _, stamps = camera(MIN_FRAMES + 5)
    out = placed(ExposureClock(), stamps)
    assert out[: MIN_FRAMES - 1] == stamps[: MIN_FRAMES - 1]
    assert all(a != b for a, b in zip(out[MIN_FRAMES:], stamps[MIN_FRAMES:], strict=True))


def test_a_stalled_frame_gets_its_exposure_not_its_late_stamp() -> None:
    exposures, stamps = camera(400)
    late = 300
    stamps[late] += 25_000_000  # a 25 ms stall in the driver
    clock = ExposureClock()
    out = placed(clock, stamps)
    assert abs(out[late] - exposures[late] - DELAY_NS) < 1.5e6  # within the usual delay
    assert clock.stats.outliers == 1
    assert clock.stats.restarts == 0
    # a stall of nearly a period: its own exposure, or the next one's, never much worse than
    # its own stamp (by the stamps' spread below the line at most)
    for stall_ns in (28_000_000, 31_000_000, 32_500_000, 40_000_000):
        exposures, stamps = camera(400)
        stamps[late] += stall_ns
        stamps[late + 1] = max(stamps[late + 1], stamps[late] + 100_000)  # delivered in order
        out = placed(ExposureClock(), stamps)
        error = abs(out[late] - exposures[late] - DELAY_NS)
        assert error < abs(stamps[late] - exposures[late] - DELAY_NS) + 1.5e6, stall_ns


@pytest.mark.parametrize("gap_ms", [190.0, 200.0, 300.0, 700.0])
@pytest.mark.parametrize(("period_ns", "phase_ns"), [(40e6, 0.0), (PERIOD_NS, -4e6)])
def test_a_camera_restarted_within_a_second_is_never_placed_on_its_old_line(
    gap_ms: float, period_ns: float, phase_ns: float
) -> None:
    _, first = camera(200)
    clock = ExposureClock()
    placed(clock, first)
    # the camera restarted after a gap: at 25 fps, or at its rate 4 ms off its old phase; its
    # new stamps are steady, so each frame belongs at its own stamp
    start = first[-1] + round(gap_ms * 1e6 + phase_ns)
    second = [start + round(i * period_ns) for i in range(100)]
    out = placed(clock, second)
    assert clock.stats.restarts == 1
    assert out == pytest.approx(second, abs=0.3e6)


def test_bursts_and_silences_are_not_a_clock() -> None:
    clock = ExposureClock()
    # a driver that hands over buffered frames in bursts of three
    stamps = [T0_NS + (i // 3) * 100_000_000 + (i % 3) * 100_000 for i in range(90)]
    assert placed(clock, stamps) == stamps
    assert clock.stats.smoothed == 0
    # a second of silence after a steady run begins again
    _, steady = camera(100)
    clock = ExposureClock()
    placed(clock, steady)
    after = steady[-1] + 2_000_000_000
    assert clock.place(after) == after
    assert clock.stats.restarts == 1


def test_a_frame_the_line_has_no_room_for_keeps_its_stamp() -> None:
    _, stamps = camera(100)
    clock = ExposureClock()
    placed(clock, stamps)
    early = stamps[-1] + 1_000_000  # a frame 1 ms after the last: no exposure of this clock
    assert EARLY_NS < PERIOD_NS / 2
    assert clock.place(early) == early  # later than the last frame's placed stamp
    assert clock.stats.outliers == 1
    assert clock.stats.restarts == 0
    # the next frames are on the line again
    nxt = stamps[-1] + round(PERIOD_NS)
    assert abs(clock.place(nxt) - nxt) < 1.5e6
    assert clock.stats.smoothed == 100 - MIN_FRAMES + 2


class ListSource:
    def __init__(self, stamps: list[int]) -> None:
        self.frames = [Frame(i, np.zeros((1, 1, 3), np.uint8), s) for i, s in enumerate(stamps)]
        self.closed = False

    def read(self) -> Frame | None:
        return self.frames.pop(0) if self.frames else None

    def close(self) -> None:
        self.closed = True


def test_the_source_wrapper_restamps_frames_and_says_so() -> None:
    exposures, stamps = camera(120)
    inner = ListSource(stamps)
    source = SteadyClockSource(inner)
    got = []
    while (frame := source.read()) is not None:
        got.append(frame.exposure_ns)
    assert got[-1] != stamps[-1]
    assert abs(got[-1] - exposures[-1] - DELAY_NS) < 1e6
    status = source.describe()
    assert set(status) == {"stamps"}  # the list says nothing of itself
    assert status["stamps"]["smoothed"] == 120 - MIN_FRAMES + 1
    source.close()
    assert inner.closed


def test_the_status_line_says_how_frames_are_stamped() -> None:
    _, stamps = camera(60)
    source = SteadyClockSource(ListSource(stamps))
    while source.read() is not None:
        pass
    text = frames_text({"frames": {"source": source.describe(), "dropped": 0}, "fps": 30.0})
    assert "stamps on the camera's clock (31 of 60, ±" in text
    assert "0 restarts" in text
    plain = frames_text({"frames": {"source": {"kind": "device", "state": "running"}}})
    assert "stamps as delivered" in plain


def test_placed_stamps_never_step_back() -> None:
    exposures, stamps = camera(100)
    clock = ExposureClock()
    placed(clock, stamps)
    # a frame delivered with the least delay: the line puts it ~0.8 ms later than its stamp
    early = round(exposures[-1] + PERIOD_NS + DELAY_NS)
    on_line = clock.place(early)
    assert on_line > early + 300_000
    burst = early + 100_000  # then one 0.1 ms after it, with no exposure of its own on the line
    assert clock.place(burst) == on_line


def test_a_line_needs_three_frames() -> None:
    with pytest.raises(ValueError, match="min_frames"):
        ExposureClock(min_frames=2)
    with pytest.raises(ValueError, match="min_frames"):
        ExposureClock(window=10, min_frames=20)
