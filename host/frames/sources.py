"""Camera sources: anything that yields frames stamped with their exposure time.

`read()` blocks (it runs in the frame loop's capture thread, never on the event loop) and
returns None at the end of a file or when the device is gone.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

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


class VideoCaptureSource:
    """OpenCV VideoCapture: a device index, a file or a stream URL."""

    def __init__(self, spec: str | int, width: int = 0, height: int = 0, fps: float = 0.0) -> None:
        import cv2

        self._cv2 = cv2
        target: str | int = int(spec) if isinstance(spec, str) and spec.isdigit() else spec
        self._cap = cv2.VideoCapture(target)
        if not self._cap.isOpened():
            raise OSError(f"camera {spec!r} could not be opened")
        for prop, value in (
            (cv2.CAP_PROP_FRAME_WIDTH, width),
            (cv2.CAP_PROP_FRAME_HEIGHT, height),
            (cv2.CAP_PROP_FPS, fps),
        ):
            if value:
                self._cap.set(prop, value)
        self._index = 0

    def read(self) -> Frame | None:
        """Grab and decode one frame, stamped when the grab returned."""
        if not self._cap.grab():
            return None
        # The exposure happened before grab() returned; the registration subtracts the
        # calibrated exposure latency from this stamp.
        stamp = time.monotonic_ns()
        ok, image = self._cap.retrieve()
        if not ok:
            return None
        self._index += 1
        return Frame(self._index, np.asarray(image, dtype=np.uint8), stamp)

    def close(self) -> None:
        """Release the capture device."""
        self._cap.release()
