"""Camera sources: anything that yields frames stamped with their exposure time.

`read()` blocks (it runs in the frame loop's capture thread, never on the event loop) and
returns None at the end of a file or when the device is gone.
"""

from __future__ import annotations

import enum
import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

Image = NDArray[np.uint8]


@dataclass(slots=True)
class Frame:
    """One captured image and when its exposure happened (host monotonic ns, mid-exposure)."""

    index: int
    image: Image
    exposure_ns: int
    truth: Any = None  # simulator ground truth, for scoring only; None on a real camera


class FrameSource(Protocol):
    """What the frame loop reads from."""

    def read(self) -> Frame | None:
        """Block until the next frame; None when the source has ended."""
        ...

    def close(self) -> None:
        """Release the device."""
        ...


def describe_source(source: object) -> dict[str, Any]:
    """What a source says of itself (its `describe()`), or nothing if it says nothing."""
    describe = getattr(source, "describe", None)
    return dict(describe()) if callable(describe) else {}


class SourceState(enum.Enum):
    """Where a camera source is in its life (shown in the status)."""

    RUNNING = "running"
    ENDED = "ended"  # a video file reached its end
    LOST = "lost"  # a device or stream stopped delivering
    CLOSED = "closed"


class VideoCaptureSource:
    """OpenCV VideoCapture: a device index, a file (played at its frame rate) or a stream URL."""

    def __init__(self, spec: str | int, width: int = 0, height: int = 0, fps: float = 0.0) -> None:
        import cv2

        self._cv2 = cv2
        target: str | int = int(spec) if isinstance(spec, str) and spec.isdigit() else spec
        self.spec = spec
        self.kind = "file" if isinstance(target, str) and Path(target).is_file() else "device"
        if isinstance(target, str) and "://" in target:
            self.kind = "stream"
        self._cap = cv2.VideoCapture(target)
        if not self._cap.isOpened():
            raise OSError(f"camera {spec!r} could not be opened")
        for prop, value in (
            (cv2.CAP_PROP_FRAME_WIDTH, width),
            (cv2.CAP_PROP_FRAME_HEIGHT, height),
            (cv2.CAP_PROP_FPS, fps),
        ):
            if value and self.kind != "file":
                self._cap.set(prop, value)
        # A file is read as fast as it decodes: pace it at its own rate, as a camera delivers.
        file_fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.fps = (file_fps if file_fps > 0 else fps) if self.kind == "file" else fps
        self.state = SourceState.RUNNING
        self.detail = ""
        self._period_ns = round(1e9 / self.fps) if self.kind == "file" and self.fps > 0 else 0
        self._next_ns = 0
        self._closed = threading.Event()
        self._index = 0

    def read(self) -> Frame | None:
        """Grab and decode one frame, stamped when the grab returned; None at the end."""
        if self._period_ns and not self._pace():
            return None
        if not self._cap.grab():
            return self._ended("no more frames")
        # The exposure happened before grab() returned; the registration subtracts the
        # calibrated exposure latency from this stamp.
        stamp = time.monotonic_ns()
        ok, image = self._cap.retrieve()
        if not ok:
            return self._ended("a frame could not be decoded")
        self._index += 1
        return Frame(self._index, np.asarray(image, dtype=np.uint8), stamp)

    def describe(self) -> dict[str, Any]:
        """Plain values for the status: what it is, its rate, whether it still delivers."""
        return {
            "source": str(self.spec),
            "kind": self.kind,
            "state": self.state.value,
            "detail": self.detail,
            "fps": self.fps,
            "frames": self._index,
        }

    def close(self) -> None:
        """Release the capture device."""
        self._closed.set()
        if self.state is SourceState.RUNNING:
            self.state = SourceState.CLOSED
        self._cap.release()

    def _pace(self) -> bool:
        """Wait for the file's next frame time (drift-free; no burst after a stall)."""
        now = time.monotonic_ns()
        if self._next_ns == 0 or self._next_ns < now - self._period_ns:
            self._next_ns = now
        delay_s = (self._next_ns - now) / 1e9
        self._next_ns += self._period_ns
        return not (delay_s > 0 and self._closed.wait(delay_s)) and not self._closed.is_set()

    def _ended(self, why: str) -> Frame | None:
        """Note why the source stopped (end of file, or a lost device) and end the loop."""
        if self.state is SourceState.RUNNING:
            self.state = SourceState.ENDED if self.kind == "file" else SourceState.LOST
            self.detail = why
            log.warning("camera source stopped", extra={"kv": {"source": self.spec, "why": why}})
        return None
