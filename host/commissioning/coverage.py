"""How well a set of board views covers the image: X, Y, size and skew, as ROS camera_calibration.

Each accepted view gives four numbers in [0, 1]: where the board sits across (x) and down (y)
the image, how much of it it fills (size) and how far the board is turned from facing the camera
(skew). A parameter's progress is the spread its views reach, over the spread that constrains
the lens well (`SPREAD`, ROS's ranges); the bars show it while views are captured and the
verdict refuses a set that does not reach `MIN_PROGRESS` in every one.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from host.geometry.camera import CameraModel
from host.geometry.transforms import FloatArray

PARAMS = ("x", "y", "size", "skew")
SPREAD = {"x": 0.7, "y": 0.7, "size": 0.4, "skew": 0.5}
# Size asks less than ROS does: a camera on a track at a fixed height can vary its distance to a
# board only by moving along the track, and for a planar board it is the tilt (skew) that
# separates the focal length from the distance (Zhang), which the skew bar asks for in full.
MIN_PROGRESS = {"x": 0.5, "y": 0.5, "size": 0.15, "skew": 0.5}
SKEW_FULL_RAD = math.radians(45.0)  # a board turned this far from facing the camera: skew 1
BAR_WIDTH = 20


@dataclass(frozen=True)
class ViewCoverage:
    """Where one view puts the board: x, y, size and skew, each in [0, 1]."""

    x: float
    y: float
    size: float
    skew: float
    rms_px: float = math.nan  # the corners' RMS about that PnP pose: the view's error, live

    def as_dict(self) -> dict[str, float]:
        """Plain values."""
        return {k: round(getattr(self, k), 4) for k in PARAMS}


def view_coverage(
    object_points: FloatArray, image_points: FloatArray, camera: CameraModel
) -> ViewCoverage:
    """The four numbers of one view; skew from a PnP pose with the (nominal) camera."""
    uv = np.asarray(image_points, dtype=np.float64)
    hull = cv2.convexHull(uv.astype(np.float32))
    area = float(cv2.contourArea(hull))
    size = math.sqrt(area / (camera.width * camera.height))
    border = math.sqrt(area)  # ROS: the board's centre can only range over the image less its size
    x = _clip((float(uv[:, 0].mean()) - border / 2) / max(camera.width - border, 1.0))
    y = _clip((float(uv[:, 1].mean()) - border / 2) / max(camera.height - border, 1.0))
    obj = np.asarray(object_points, np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, uv, camera.K, camera.dist, flags=cv2.SOLVEPNP_SQPNP)
    skew, rms = 0.0, math.nan
    if ok:
        normal = cv2.Rodrigues(rvec)[0][:, 2]
        tilt = math.acos(min(1.0, abs(float(normal[2]))))
        skew = _clip(tilt / SKEW_FULL_RAD)
        seen = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist)[0].reshape(-1, 2)
        rms = math.sqrt(float(np.mean(np.sum((seen - uv) ** 2, axis=1))))
    return ViewCoverage(x, y, _clip(size), skew, rms)


def progress(views: Sequence[ViewCoverage]) -> dict[str, float]:
    """Per parameter: the spread reached over the spread wanted, capped at 1."""
    if not views:
        return dict.fromkeys(PARAMS, 0.0)
    out = {}
    for key in PARAMS:
        vals = [getattr(v, key) for v in views]
        out[key] = round(min((max(vals) - min(vals)) / SPREAD[key], 1.0), 3)
    return out


def shortfall(prog: dict[str, float]) -> list[str]:
    """The parameters whose progress is below MIN_PROGRESS, as readable phrases."""
    return [
        f"{key} coverage {prog[key]:.2f} < {MIN_PROGRESS[key]:.2f}"
        for key in PARAMS
        if prog.get(key, 0.0) < MIN_PROGRESS[key]
    ]


def bars(prog: dict[str, float]) -> str:
    """`X [#####-----] 0.50` lines, one per parameter."""
    lines = []
    for key in PARAMS:
        filled = round(BAR_WIDTH * prog.get(key, 0.0))
        mark = "ok" if prog.get(key, 0.0) >= MIN_PROGRESS[key] else ".."
        lines.append(
            f"{key:>4} [{'#' * filled}{'-' * (BAR_WIDTH - filled)}] {prog.get(key, 0.0):.2f} {mark}"
        )
    return "\n".join(lines)


def _clip(v: float) -> float:
    return min(max(v, 0.0), 1.0)
