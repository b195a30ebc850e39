"""The daemon's camera as the commissioning sees it: the newest frame, and waiting for a new one.

`FrameTap` wraps the frame loop's source: every frame the loop reads is also kept as the newest,
so a calibration can take a frame exposed after the head came to rest without a second reader
on the camera. Frames are stamped as the camera stamps them (`Frame.exposure_ns`); until the
latency is calibrated a stamp may lag the exposure, so `wait_frame` adds a margin.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from typing import Any

from host.frames.sources import Frame, FrameSource, describe_source

POLL_S = 0.01


class FrameTap:
    """A FrameSource that remembers the newest frame it passed on (thread-safe)."""

    def __init__(self, source: FrameSource) -> None:
        self.source = source
        self._lock = threading.Lock()
        self._latest: Frame | None = None
        self.frames = 0

    def read(self) -> Frame | None:
        """Read from the camera and keep the frame."""
        frame = self.source.read()
        if frame is not None:
            with self._lock:
                self._latest = frame
                self.frames += 1
        return frame

    def close(self) -> None:
        """Release the camera."""
        self.source.close()

    def describe(self) -> dict[str, Any]:
        """The camera's own description (`orbitar status` shows it)."""
        return describe_source(self.source)

    def latest(self) -> Frame | None:
        """The newest frame, or None before the first."""
        with self._lock:
            return self._latest

    def offer(self, frame: Frame) -> None:
        """Keep a frame read elsewhere (a loop that renders its own frames)."""
        with self._lock:
            self._latest = frame
            self.frames += 1


class NoFramesError(RuntimeError):
    """The camera delivered nothing usable in time."""


async def wait_frame(
    tap: FrameTap, after_ns: int, timeout_s: float, on_poll: Callable[[], None] | None = None
) -> Frame:
    """The first frame stamped after `after_ns`; NoFramesError after `timeout_s`. `on_poll`
    is called at every look (e.g. to read the head while it stands waiting)."""
    deadline = time.monotonic() + timeout_s
    while True:
        if on_poll is not None:
            on_poll()
        frame = tap.latest()
        if frame is not None and frame.exposure_ns > after_ns and frame.image.size > 16:
            return frame
        if time.monotonic() >= deadline:
            got = "no frame at all" if frame is None else "no new frame"
            raise NoFramesError(f"camera: {got} within {timeout_s:.1f} s")
        await asyncio.sleep(POLL_S)


class RangeTap:
    """A controller sample sink keeping the newest rangefinder readings and reference-mark
    captures (thread-safe)."""

    def __init__(self, keep: int = 256) -> None:
        self._lock = threading.Lock()
        self._keep = keep
        self._readings: list[tuple[int, float, int]] = []
        self._marks: list[tuple[int, float]] = []

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """Not needed here."""

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """Not needed here."""

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """Keep a mark's captured encoder position (the controller's mm)."""
        with self._lock:
            self._marks.append((t_host_ns, s_mm))
            del self._marks[: -self._keep]

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """Keep a reading."""
        with self._lock:
            self._readings.append((t_host_ns, distance_mm, quality))
            del self._readings[: -self._keep]

    def since(self, t_ns: int) -> list[tuple[int, float, int]]:
        """Readings taken after t_ns, oldest first."""
        with self._lock:
            return [r for r in self._readings if r[0] > t_ns]

    def marks_since(self, t_ns: int) -> list[tuple[int, float]]:
        """Mark captures (host time, controller position mm) after t_ns, oldest first."""
        with self._lock:
            return [m for m in self._marks if m[0] > t_ns]


async def wait_ranges(tap: RangeTap, after_ns: int, count: int, timeout_s: float) -> list[float]:
    """`count` valid (quality > 0) distances read after `after_ns`; NoFramesError on timeout."""
    deadline = time.monotonic() + timeout_s
    while True:
        got = [d for _, d, q in tap.since(after_ns) if q > 0]
        if len(got) >= count:
            return got[:count]
        if time.monotonic() >= deadline:
            raise NoFramesError(
                f"rangefinder: {len(got)} of {count} readings within {timeout_s:.1f} s"
            )
        await asyncio.sleep(POLL_S)


def attach_range_tap(controller: object) -> RangeTap:
    """A RangeTap on a controller's samples, kept as its `range_tap` for the commissioning."""
    tap = RangeTap()
    controller.add_sink(tap)  # type: ignore[attr-defined]
    setattr(controller, "range_tap", tap)  # noqa: B010
    return tap
