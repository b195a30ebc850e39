"""Draw a projected wireframe onto a BGR uint8 frame.

Edges are clipped in 3D against the near plane (z = MIN_DEPTH_MM) before projection, so an edge
with one vertex behind the camera is drawn up to where it leaves the view instead of wrapping
through infinity; edges wholly behind are dropped. Projected segments are then clipped to the
image (plus a margin) so they fit OpenCV's fixed-point coordinates. Edges are drawn as straight
chords between projected end points; under distortion a long edge is really a slight curve.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from host.geometry.camera import MIN_DEPTH_MM, CameraModel, Projector
from host.geometry.model import Wireframe
from host.geometry.transforms import ArrayLike, FloatArray

UInt8Image = npt.NDArray[np.uint8]

SHIFT_BITS = 4  # sub-pixel bits handed to cv2.polylines (1/16 px)
CLIP_MARGIN_PX = 8.0  # keep a little beyond the border so clipped ends are not visible
DEFAULT_COLOR_BGR = (0, 255, 0)


@dataclass(frozen=True)
class OverlayStyle:
    """Line colour (BGR), thickness in pixels and anti-aliasing."""

    color: tuple[int, int, int] = DEFAULT_COLOR_BGR
    thickness: int = 1
    antialias: bool = False


class WireframeOverlay:
    """Projects one model for each frame and draws it; buffers are reused across frames."""

    def __init__(self, camera: CameraModel, model: Wireframe) -> None:
        self.camera = camera
        self.model = model
        self._projector = Projector(camera, model.vertices)
        self._a = np.ascontiguousarray(model.edges[:, 0])
        self._b = np.ascontiguousarray(model.edges[:, 1])

    def segments(self, T_c_w: ArrayLike) -> FloatArray:
        """Image segments (K,2,2) of the visible part of each edge, in pixels."""
        uv, valid = self._projector.project(np.asarray(T_c_w, dtype=np.float64))
        va, vb = valid[self._a], valid[self._b]
        both = va & vb
        seg = np.stack([uv[:, self._a[both]].T, uv[:, self._b[both]].T], axis=1)
        one = va ^ vb
        if np.any(one):
            seg = np.concatenate([seg, self._near_clipped(T_c_w, one, va)])
        return clip_segments(seg, self.camera.width, self.camera.height, CLIP_MARGIN_PX)

    def draw(self, frame: UInt8Image, T_c_w: ArrayLike, style: OverlayStyle | None = None) -> int:
        """Draw the model seen from T_c_w into frame in place; returns the segment count."""
        seg = self.segments(T_c_w)
        return draw_segments(frame, seg, style or OverlayStyle())

    def _near_clipped(
        self, T_c_w: ArrayLike, one: npt.NDArray[np.bool_], va: npt.NDArray[np.bool_]
    ) -> FloatArray:
        """Segments of edges crossing the near plane, cut at z = MIN_DEPTH_MM."""
        T = np.asarray(T_c_w, dtype=np.float64)
        v = self.model.vertices
        front = np.where(va[one], self._a[one], self._b[one])
        back = np.where(va[one], self._b[one], self._a[one])
        pf = v[front] @ T[:3, :3].T + T[:3, 3]
        pb = v[back] @ T[:3, :3].T + T[:3, 3]
        f = (pf[:, 2] - MIN_DEPTH_MM) / (pf[:, 2] - pb[:, 2])
        cut = pf + f[:, None] * (pb - pf)
        cut[:, 2] = MIN_DEPTH_MM  # exact, so rounding cannot push it behind the plane
        uf, _ = self.camera.project(pf)
        uc, _ = self.camera.project(cut)
        return np.stack([uf, uc], axis=1)


def clip_segments(seg: FloatArray, width: int, height: int, margin: float) -> FloatArray:
    """Liang-Barsky clip of segments (K,2,2) to the image rectangle grown by margin."""
    p0, d = seg[:, 0], seg[:, 1] - seg[:, 0]
    lo = np.array([-margin, -margin])
    hi = np.array([width - 1 + margin, height - 1 + margin])
    t0 = np.zeros(len(seg))
    t1 = np.ones(len(seg))
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis in range(2):
            dd = d[:, axis]
            ta = (lo[axis] - p0[:, axis]) / dd
            tb = (hi[axis] - p0[:, axis]) / dd
            t_enter, t_exit = np.minimum(ta, tb), np.maximum(ta, tb)
            parallel = dd == 0.0
            inside = (p0[:, axis] >= lo[axis]) & (p0[:, axis] <= hi[axis])
            t_enter = np.where(parallel, np.where(inside, -np.inf, np.inf), t_enter)
            t_exit = np.where(parallel, np.where(inside, np.inf, -np.inf), t_exit)
            t0 = np.maximum(t0, t_enter)
            t1 = np.minimum(t1, t_exit)
    keep = (t0 <= t1) & np.isfinite(p0).all(axis=1) & np.isfinite(d).all(axis=1)
    p0, d, t0, t1 = p0[keep], d[keep], t0[keep], t1[keep]
    return np.stack([p0 + t0[:, None] * d, p0 + t1[:, None] * d], axis=1)


def draw_segments(frame: UInt8Image, seg: FloatArray, style: OverlayStyle) -> int:
    """Draw clipped segments (K,2,2) in pixels with sub-pixel precision; returns K."""
    if len(seg) == 0:
        return 0
    pts = np.rint(seg * (1 << SHIFT_BITS)).astype(np.int32)
    line_type = cv2.LINE_AA if style.antialias else cv2.LINE_8
    cv2.polylines(frame, list(pts), False, style.color, style.thickness, line_type, SHIFT_BITS)
    return len(seg)


def draw_wireframe(
    frame: UInt8Image,
    camera: CameraModel,
    model: Wireframe,
    T_c_w: ArrayLike,
    style: OverlayStyle | None = None,
) -> int:
    """Project and draw a model once (allocates: use WireframeOverlay in a frame loop)."""
    return WireframeOverlay(camera, model).draw(frame, T_c_w, style)
