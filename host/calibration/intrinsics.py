"""Camera intrinsics from chessboard views (cv2.calibrateCameraExtended).

OpenCV estimates no skew, so the result has skew 0 (Table 1's r = 0.263 px moves a pixel by at
most 0.04 px over this sensor: below what a chessboard resolves). The paper models k1, k2 only,
so k3 and the tangential terms are fixed at zero unless `full_distortion` is set.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from host.geometry.camera import CameraModel
from host.geometry.transforms import FloatArray, make_T

SUBPIX_WINDOW_PX = 7  # half-size of the cornerSubPix search window
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
MIN_VIEWS = 3
STD_KEYS = ("fx", "fy", "u0", "v0", "k1", "k2", "p1", "p2", "k3")  # OpenCV's order


@dataclass(frozen=True)
class IntrinsicsResult:
    """Calibrated camera, one-sigma uncertainties, RMS and per-view board poses."""

    camera: CameraModel
    std: dict[str, float]
    rms_px: float
    per_view_rms_px: FloatArray
    T_c_b: list[FloatArray] = field(default_factory=list)

    def to_config(self) -> dict[str, Any]:
        """{"camera": {fx, fy, skew, u0, v0, k1, k2, p1, p2, k3, width, height}}."""
        return {"camera": self.camera.to_config()}


def find_chessboard(image: npt.NDArray[np.uint8], pattern: tuple[int, int]) -> FloatArray | None:
    """Inner corners (cols*rows, 2) refined to sub-pixel, or None if the board is not found."""
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, pattern, flags=flags)
    if not found:
        return None
    win = (SUBPIX_WINDOW_PX, SUBPIX_WINDOW_PX)
    refined = cv2.cornerSubPix(gray, corners, win, (-1, -1), SUBPIX_CRITERIA)
    return np.asarray(refined, dtype=np.float64).reshape(-1, 2)


def calibrate_intrinsics(
    object_points: list[FloatArray],
    image_points: list[FloatArray],
    image_size: tuple[int, int],
    full_distortion: bool = False,
) -> IntrinsicsResult:
    """Calibrate from per-view board points (N,3) and their pixels (N,2); size = (w, h)."""
    if len(object_points) != len(image_points) or len(object_points) < MIN_VIEWS:
        raise ValueError(f"need ≥ {MIN_VIEWS} views with matching object and image points")
    obj = [np.asarray(p, dtype=np.float32).reshape(-1, 1, 3) for p in object_points]
    img = [np.asarray(p, dtype=np.float32).reshape(-1, 1, 2) for p in image_points]
    flags = 0 if full_distortion else cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    rms, K, dist, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
        obj, img, image_size, np.eye(3), np.zeros(5), flags=flags
    )
    d = np.zeros(5)
    d[: min(5, dist.size)] = dist.ravel()[:5]
    camera = CameraModel(
        fx=float(K[0, 0]), fy=float(K[1, 1]), skew=0.0, u0=float(K[0, 2]), v0=float(K[1, 2]),
        k1=float(d[0]), k2=float(d[1]), p1=float(d[2]), p2=float(d[3]), k3=float(d[4]),
        width=int(image_size[0]), height=int(image_size[1]),
    )  # fmt: skip
    std = {k: float(v) for k, v in zip(STD_KEYS, std_in.ravel(), strict=False)}
    poses = [make_T(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs, strict=True)]
    return IntrinsicsResult(camera, std, float(rms), per_view.ravel().astype(np.float64), poses)
