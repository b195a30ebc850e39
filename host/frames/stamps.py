"""Frame stamps of a free-running camera, put back on the camera's own exposure clock.

A camera without a trigger is stamped when its frame reaches the host: the readout, the
transfer and the driver's scheduling late, by a delay that varies from frame to frame (about a
millisecond over USB, more on a busy host). The exposures themselves come off the sensor's
crystal at a steady period. At the trolley's 0.5 m/s a millisecond is half a millimetre along
the track, the largest error left in a moving overlay, so the host fits the steady clock to the
stamps and uses the fit instead of each frame's own stamp, as broadcast trackers and camera
drivers smooth timestamps for the same reason.

The fit is a least-squares line of stamp against frame number over the last WINDOW_FRAMES
frames. A frame's number is counted in periods on the line, so a frame the camera or the driver
dropped leaves a gap instead of shifting the line by a period, and a frame held back by a stall
is left out of the fit but still gets its place on the line. After two or more frames lost in a
row the next three must sit on the line again before it stands for them (a camera restarted
within the second, at another rate or phase). Through the mean of the stamps the
line keeps their mean delay, which the calibrated exposure latency takes off as before. Where
the stamps are not those of a steady clock (frames that come in bursts, a camera restarted at
another rate, a gap of a second), the clock starts again and passes the stamps through as given
until it has MIN_FRAMES on its new line: never a guess.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from host.frames.sources import Frame, FrameSource, describe_source

WINDOW_FRAMES = 300  # 10 s at 30 fps: the line's σ at its newest frame is ~2σ/√300 of a stamp's
MIN_FRAMES = 30  # frames on one line before it replaces their stamps
AMBIGUOUS_PERIODS = 0.3  # a step this far from a whole number of periods is not the clock's
MAX_GAP_NS = 1_000_000_000  # after a longer silence the camera may have restarted
OUTLIER_NS = 5_000_000  # a stamp this far off the line (a stall) is not fitted
EARLY_NS = 3_000_000  # the earliest a stamp comes before the line (its mean delay), at most
SPREAD_SLACK_NS = 500_000  # beyond the fitted stamps' own spread about the line
PROBATION_FRAMES = 3  # after a gap of frames, this many must sit on the line again
PROBATION_LATE_NS = 2_000_000  # ... no later than the fitted spread, or this
RECENT_FRAMES = 10  # of the last this many frames,
OFF_LINE_FRAMES = 5  # this many off the line are not a stall: the clock changed
MIN_PERIOD_NS = 2_000_000  # 500 fps: steps shorter than this are a driver's burst
MAX_STEP_PERIODS = 8  # more frames lost in a row than this, and the count is not trusted
MAX_RESIDUAL_PERIODS = 0.1  # a line the stamps scatter about by more than this is no clock


@dataclass
class StampStats:
    """What the exposure clock did with the stamps (for the status)."""

    frames: int = 0
    smoothed: int = 0  # stamps replaced by the line
    restarts: int = 0  # times the stamps left the line and it began again
    # stamps later than the line by more than OUTLIER_NS (placed on it), or with no exposure of
    # their own on it (kept as given)
    outliers: int = 0
    period_us: float = 0.0  # the fitted period
    residual_us: float = 0.0  # RMS of the fitted stamps about the line


class ExposureClock:
    """Fits a steady frame clock to delivery stamps; `place` gives a frame's stamp on it."""

    def __init__(self, window: int = WINDOW_FRAMES, min_frames: int = MIN_FRAMES) -> None:
        if not 3 <= min_frames <= window:
            raise ValueError(f"need 3 <= min_frames <= window, got {min_frames} and {window}")
        self.window = window
        self.min_frames = min_frames
        self.stats = StampStats()
        self._numbers: deque[int] = deque(maxlen=window)
        self._stamps: deque[int] = deque(maxlen=window)
        self._period_ns = 0.0  # 0 until two frames have been seen
        # fitted: (the line's stamp at frame number n0, the period, n0)
        self._line: tuple[float, float, int] | None = None
        self._early_ns = float(EARLY_NS)  # the most a stamp of this camera comes before the line
        self._late_ns = float(OUTLIER_NS)  # the most it comes after, but for a stall
        self._recent_off: deque[bool] = deque(maxlen=RECENT_FRAMES)  # frames off the line
        self._probation = 0  # frames after a gap that must sit on the line before it is used
        self._last_out: int | None = None

    def place(self, stamp_ns: int) -> int:
        """The stamp of this frame on the camera's clock (or as given, until the clock is known)."""
        self.stats.frames += 1
        out = self._warm_up(stamp_ns) if self._line is None else self._on_line(stamp_ns)
        if self._last_out is not None and self._last_out - EARLY_NS < out < self._last_out:
            out = self._last_out  # frames come in order: a stamp kept as given never steps back
            # behind a placed one (a stamp that itself went back further is passed on as it is)
        self._last_out = out
        return out

    def _on_line(self, stamp_ns: int) -> int:
        """A frame once the line is known: its place on it, or its own stamp if it has none."""
        assert self._line is not None
        last_number, last_stamp = self._numbers[-1], self._stamps[-1]
        if stamp_ns - last_stamp > MAX_GAP_NS:
            return self._restart(stamp_ns)
        # A stamp comes before the line by at most the delay's spread below its mean, so the
        # frame is the latest the line allows: a frame late by a stall gets its own exposure,
        # or the next one's if the stall was within that spread of a whole period.
        icept, period, n0 = self._line
        number = n0 + math.floor((stamp_ns - icept + self._early_ns) / period)
        late = stamp_ns - self._at(number)
        if number - last_number > 2:
            # Frames lost in a row, or the camera restarted at another phase or rate: the
            # next frames must sit on the line before it stands for them again.
            self._probation = PROBATION_FRAMES
        if self._probation:
            if number <= last_number or late > self._late_ns:
                return self._restart(stamp_ns)
            self._probation -= 1
            self._numbers.append(number)
            self._stamps.append(stamp_ns)
            return stamp_ns
        fits = number > last_number
        off = not fits or late > OUTLIER_NS
        self._recent_off.append(off)
        self.stats.outliers += off
        if sum(self._recent_off) >= OFF_LINE_FRAMES:  # not a stall: the clock itself changed
            return self._restart(stamp_ns)
        if not fits:  # on the last frame's exposure, or before it: keep the stamp it came with
            return stamp_ns
        self._numbers.append(number)
        self._stamps.append(stamp_ns)
        if not self._fit():
            return self._restart(stamp_ns)
        self.stats.smoothed += 1
        return round(self._at(number))

    def _warm_up(self, stamp_ns: int) -> int:
        """Before the line: number the frames by their steps, and fit once there are enough."""
        if not self._stamps:
            return self._restart(stamp_ns)
        step = stamp_ns - self._stamps[-1]
        if len(self._stamps) == 1:  # the second frame: its step sets the first period
            if not MIN_PERIOD_NS <= step <= MAX_GAP_NS:
                return self._restart(stamp_ns)
            self._period_ns = float(step)
        periods = step / self._period_ns
        whole = round(periods)
        if not 1 <= whole <= MAX_STEP_PERIODS or abs(periods - whole) > AMBIGUOUS_PERIODS:
            return self._restart(stamp_ns)
        self._numbers.append(self._numbers[-1] + whole)
        self._stamps.append(stamp_ns)
        # the period over all the frames so far, not the first step's
        self._period_ns = (stamp_ns - self._stamps[0]) / (self._numbers[-1] - self._numbers[0])
        if len(self._stamps) < self.min_frames:
            return stamp_ns
        if not self._fit():
            return self._restart(stamp_ns)
        self.stats.smoothed += 1
        return round(self._at(self._numbers[-1]))

    def _fit(self) -> bool:
        """The least-squares line through the window, refitted without the stalled stamps;
        False if the stamps are too far about it to be a clock's."""
        n0, t0 = self._numbers[0], self._stamps[0]  # relative: a day is 2.6 million frames
        n = np.asarray([k - n0 for k in self._numbers], np.float64)
        t = np.asarray([s - t0 for s in self._stamps], np.float64)
        keep = np.ones(len(n), bool)
        for _ in range(2):
            nk, tk = n[keep], t[keep]
            n_mean, t_mean = nk.mean(), tk.mean()
            slope = float(((nk - n_mean) * (tk - t_mean)).sum() / ((nk - n_mean) ** 2).sum())
            icept = t_mean - slope * n_mean
            resid = t - (icept + slope * n)
            keep = np.abs(resid) <= OUTLIER_NS
            if keep.sum() < max(3, len(keep) // 2):  # no line through most of them
                keep[:] = True
        self._period_ns = float(slope)
        self._line = (float(icept) + t0, float(slope), n0)
        rms = float(np.sqrt(np.mean(resid[keep] ** 2)))
        self._early_ns = min(float(EARLY_NS), max(-float(resid[keep].min()), 0.0) + SPREAD_SLACK_NS)
        self._late_ns = max(float(resid[keep].max()) + SPREAD_SLACK_NS, PROBATION_LATE_NS)
        self.stats.period_us = self._period_ns / 1e3
        self.stats.residual_us = rms / 1e3
        return slope >= MIN_PERIOD_NS and rms <= MAX_RESIDUAL_PERIODS * slope

    def _at(self, number: int) -> float:
        """The line's stamp at a frame number."""
        assert self._line is not None
        icept, slope, n0 = self._line
        return icept + slope * (number - n0)

    def _restart(self, stamp_ns: int) -> int:
        """Begin a new line at this frame, which keeps its stamp (the old line no longer
        describes the stamps, or there was none)."""
        if self._stamps:
            self.stats.restarts += 1
        self._numbers.clear()
        self._stamps.clear()
        self._numbers.append(0)
        self._stamps.append(stamp_ns)
        self._period_ns = 0.0
        self._line = None
        self._recent_off.clear()
        self._probation = 0
        self._early_ns, self._late_ns = float(EARLY_NS), float(OUTLIER_NS)
        return stamp_ns


class SteadyClockSource:
    """A frame source whose frames carry their stamps on the camera's exposure clock."""

    def __init__(self, source: FrameSource, clock: ExposureClock | None = None) -> None:
        self.inner = source
        self.clock = clock or ExposureClock()

    def read(self) -> Frame | None:
        """The next frame of the camera, its stamp placed on the fitted clock."""
        frame = self.inner.read()
        if frame is not None:
            frame.exposure_ns = self.clock.place(frame.exposure_ns)
        return frame

    def close(self) -> None:
        """Release the camera."""
        self.inner.close()

    def describe(self) -> dict[str, Any]:
        """The camera's own description, and what the clock did with its stamps."""
        return {**describe_source(self.inner), "stamps": asdict(self.clock.stats)}
