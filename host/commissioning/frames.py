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

from host.frames.sources import Frame, FrameSource

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


async def wait_frame(tap: FrameTap, after_ns: int, timeout_s: float) -> Frame:
    """The first frame stamped after `after_ns`; NoFramesError after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        frame = tap.latest()
        if frame is not None and frame.exposure_ns > after_ns and frame.image.size > 16:
            return frame
        if time.monotonic() >= deadline:
            got = "no frame at all" if frame is None else "no new frame"
            raise NoFramesError(f"camera: {got} within {timeout_s:.1f} s")
        await asyncio.sleep(POLL_S)
