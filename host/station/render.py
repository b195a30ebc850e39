"""What the station shows: the frame (or a plain background) with the registered overlay, as JPEG.

Runs in the station's encoder thread, never on the event loop. The overlay is the model's edges
from the registered pose, the feature points with their labels, and optionally the
encoder-only registration as a ghost, so the drift correction can be seen.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from host.geometry.camera import CameraModel
from host.geometry.model import Wireframe
from host.geometry.transforms import FloatArray, invert_T, transform_points
from host.registration.overlay import OverlayStyle, WireframeOverlay
from host.station.parts import Parts

Image = NDArray[np.uint8]

BACKGROUND_BGR = (48, 40, 36)  # without a camera: a dark plain background
MODEL_STYLE = OverlayStyle(color=(80, 255, 80), thickness=2, antialias=True)
GHOST_STYLE = OverlayStyle(color=(200, 120, 255), thickness=1, antialias=True)
POINT_BGR = (255, 0, 255)  # magenta: the feature points (the browser tests look for it)
POINT_RADIUS_PX = 7
LABEL_BGR = (255, 255, 255)
FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class ViewInput:
    """One thing to show: an image (None: no camera) and the pose registered for it."""

    index: int
    exposure_ns: int  # host monotonic ns of the exposure this view shows
    image: Image | None
    T_w_c: FloatArray | None  # None: the frame had no usable pose (no overlay, never a guess)
    T_w_c_ghost: FloatArray | None = None  # encoder-only pose, before the drift correction
    s_mm: float | None = None


@dataclass(frozen=True)
class EncodedView:
    """A JPEG ready to send, with what the page shows beside it."""

    index: int
    exposure_ns: int
    jpeg: bytes
    width: int
    height: int
    points_uv: dict[str, tuple[float, float]]  # feature points in view, pixels
    cpu_ms: float  # this thread's CPU time to draw and encode
    encoded_ns: int  # host monotonic ns when the JPEG was ready
    registered: bool
    ghost: bool = False  # the encoder-only registration is drawn in it


class ViewRenderer:
    """Draws and encodes views for one camera, model and workpiece pose."""

    def __init__(
        self,
        camera: CameraModel,
        model: Wireframe,
        T_w_p: FloatArray,
        parts: Parts,
        jpeg_quality: int = 80,
    ) -> None:
        self.camera = camera
        self.T_w_p = np.asarray(T_w_p, dtype=np.float64)
        self.parts = parts
        self.jpeg_quality = jpeg_quality
        self._overlay = WireframeOverlay(camera, model)
        self._names = [p.name for p in parts.points]
        self._points_p = np.array([p.position_mm for p in parts.points], dtype=np.float64)
        self._background: Image | None = None

    def render(self, view: ViewInput, ghost: bool = True) -> EncodedView:
        """Draw the overlay (with the ghost, if asked and known) on a copy and encode it."""
        t0 = time.thread_time_ns()
        image = self._canvas(view.image)
        points: dict[str, tuple[float, float]] = {}
        ghost = ghost and view.T_w_c is not None and view.T_w_c_ghost is not None
        if view.T_w_c is not None:
            if ghost and view.T_w_c_ghost is not None:
                self._overlay.draw(image, self._T_c_p(view.T_w_c_ghost), GHOST_STYLE)
            T_c_p = self._T_c_p(view.T_w_c)
            self._overlay.draw(image, T_c_p, MODEL_STYLE)
            points = self.project_points(T_c_p)
            self._draw_points(image, points)
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        cpu_ms = (time.thread_time_ns() - t0) / 1e6
        h, w = image.shape[:2]
        return EncodedView(
            view.index,
            view.exposure_ns,
            buf.tobytes(),
            w,
            h,
            points,
            cpu_ms,
            time.monotonic_ns(),
            view.T_w_c is not None,
            ghost,
        )

    def project_points(self, T_c_p: FloatArray) -> dict[str, tuple[float, float]]:
        """The feature points that fall in the image, by name, in pixels."""
        if not self._names:
            return {}
        uv, valid = self.camera.project(transform_points(T_c_p, self._points_p))
        out = {}
        for name, (u, v), ok in zip(self._names, uv, valid, strict=True):
            if ok and 0 <= u < self.camera.width and 0 <= v < self.camera.height:
                out[name] = (round(float(u), 2), round(float(v), 2))
        return out

    def _T_c_p(self, T_w_c: FloatArray) -> FloatArray:
        """Workpiece in the camera."""
        out: FloatArray = invert_T(np.asarray(T_w_c, dtype=np.float64)) @ self.T_w_p
        return out

    def _canvas(self, image: Image | None) -> Image:
        """A writable copy of the frame at the camera's size, or the plain background."""
        size = (self.camera.width, self.camera.height)
        if image is None:
            if self._background is None:
                self._background = np.empty((size[1], size[0], 3), np.uint8)
                self._background[:] = BACKGROUND_BGR
            return self._background.copy()
        if image.ndim == 2:
            image = np.asarray(cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), np.uint8)
        if (image.shape[1], image.shape[0]) != size:
            return np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), np.uint8)
        return image.copy()

    @staticmethod
    def _draw_points(image: Image, points: dict[str, tuple[float, float]]) -> None:
        """A filled marker and an outlined label per feature point."""
        for name, (u, v) in points.items():
            centre = (round(u), round(v))
            cv2.circle(image, centre, POINT_RADIUS_PX, POINT_BGR, -1, cv2.LINE_AA)
            org = (centre[0] + POINT_RADIUS_PX + 4, centre[1] - POINT_RADIUS_PX)
            cv2.putText(image, name, org, FONT, 0.7, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(image, name, org, FONT, 0.7, LABEL_BGR, 2, cv2.LINE_AA)
