"""Camera intrinsics with the paper's skew r, from board views, with standard deviations.

OpenCV's calibrateCamera has no skew term, so it only gives the start: a Levenberg-Marquardt pass
(host.calibration.lsq) then refines fx, fy, skew, u0, v0, k1, k2 (and p1, p2, k3 when asked)
jointly with every view's board pose on the reprojection error of all corners. The standard
deviations come from that Jacobian, (JᵀJ)⁻¹ scaled by the residual variance. Views may hold any
subset of the board's corners (ChArUco), so each view's points are its own arrays.

Views whose RMS is far above the others' (a misdetected corner, a view taken while the head was
still ringing) are dropped and the solve repeated: `calibrate_with_rejection`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from host.calibration import lsq
from host.geometry.camera import CameraModel
from host.geometry.transforms import FloatArray, make_T, rotvec_to_R

SUBPIX_WINDOW_PX = 7  # half-size of the cornerSubPix search window
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
MIN_VIEWS = 3
BASE_KEYS = ("fx", "fy", "skew", "u0", "v0", "k1", "k2")  # the paper's Table 1
FULL_KEYS = (*BASE_KEYS, "p1", "p2", "k3")
# forward-difference steps: pixels for K, unitless for distortion, rad and mm for poses
STEPS = {"fx": 1e-3, "fy": 1e-3, "skew": 1e-3, "u0": 1e-3, "v0": 1e-3}
DIST_STEP = 1e-7
POSE_STEPS = np.array([1e-7, 1e-7, 1e-7, 1e-4, 1e-4, 1e-4])
OUTLIER_FACTOR = 3.0  # a view this many times the median view RMS is an outlier...
OUTLIER_FLOOR_PX = 0.3  # ...if it is also above this (sub-tenth-pixel views all look alike)
MAX_REJECTION_ROUNDS = 3


@dataclass(frozen=True)
class IntrinsicsResult:
    """Calibrated camera, one-sigma uncertainties and covariance, residuals per view."""

    camera: CameraModel
    std: dict[str, float]
    rms_px: float
    per_view_rms_px: FloatArray
    T_c_b: list[FloatArray] = field(default_factory=list)
    keys: tuple[str, ...] = BASE_KEYS
    covariance: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    residuals_px: list[FloatArray] = field(default_factory=list)  # per view (N,2)
    opencv_rms_px: float = float("nan")  # the skew-free start, for the report
    rejected_views: tuple[int, ...] = ()  # indices into the views given

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
    object_points: Sequence[FloatArray],
    image_points: Sequence[FloatArray],
    image_size: tuple[int, int],
    full_distortion: bool = False,
) -> IntrinsicsResult:
    """Calibrate from per-view board points (N,3, z = 0) and pixels (N,2); size = (w, h)."""
    if len(object_points) != len(image_points) or len(object_points) < MIN_VIEWS:
        raise ValueError(
            f"need ≥ {MIN_VIEWS} views with matching object and image points, "
            f"got {len(object_points)} and {len(image_points)}"
        )
    obj = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in object_points]
    img = [np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in image_points]
    start, poses0, cv_rms = _opencv_start(obj, img, image_size, full_distortion)
    keys = FULL_KEYS if full_distortion else BASE_KEYS
    problem = _Problem(obj, img, image_size, keys)
    x0 = np.concatenate([[getattr(start, k) for k in keys], *poses0])
    sol = lsq.solve(problem.residuals, x0, problem.jacobian)
    k = len(keys)
    camera = problem.camera(sol.x[:k])
    cov = sol.covariance[:k, :k]
    res = problem.split(sol.residuals)
    per_view = np.array([float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) for r in res])
    all_r = np.concatenate(res)
    rms = float(np.sqrt(np.mean(np.sum(all_r * all_r, axis=1))))
    poses = [_pose_T(sol.x[k + 6 * i : k + 6 * i + 6]) for i in range(len(obj))]
    std = {key: float(s) for key, s in zip(keys, np.sqrt(np.diag(cov)), strict=True)}
    return IntrinsicsResult(camera, std, rms, per_view, poses, keys, cov, res, cv_rms)


def calibrate_with_rejection(
    object_points: Sequence[FloatArray],
    image_points: Sequence[FloatArray],
    image_size: tuple[int, int],
    full_distortion: bool = False,
) -> IntrinsicsResult:
    """Calibrate, drop outlier views by per-view RMS, repeat until none is left to drop."""
    keep = list(range(len(object_points)))
    for _ in range(MAX_REJECTION_ROUNDS):
        res = calibrate_intrinsics(
            [object_points[i] for i in keep], [image_points[i] for i in keep], image_size,
            full_distortion,
        )  # fmt: skip
        limit = max(OUTLIER_FACTOR * float(np.median(res.per_view_rms_px)), OUTLIER_FLOOR_PX)
        bad = [keep[j] for j, e in enumerate(res.per_view_rms_px) if e > limit]
        if not bad or len(keep) - len(bad) < MIN_VIEWS:
            break
        keep = [i for i in keep if i not in bad]
    rejected = tuple(i for i in range(len(object_points)) if i not in keep)
    return _with_rejected(res, rejected)


def _with_rejected(res: IntrinsicsResult, rejected: tuple[int, ...]) -> IntrinsicsResult:
    """The same result, naming the dropped views."""
    return IntrinsicsResult(
        res.camera, res.std, res.rms_px, res.per_view_rms_px, res.T_c_b, res.keys,
        res.covariance, res.residuals_px, res.opencv_rms_px, rejected,
    )  # fmt: skip


def _opencv_start(
    obj: list[FloatArray], img: list[FloatArray], size: tuple[int, int], full: bool
) -> tuple[CameraModel, list[FloatArray], float]:
    """OpenCV's skew-free calibration: the starting camera and per-view (rvec, t)."""
    o32 = [p.astype(np.float32).reshape(-1, 1, 3) for p in obj]
    i32 = [p.astype(np.float32).reshape(-1, 1, 2) for p in img]
    flags = 0 if full else cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        o32, i32, size, np.eye(3), np.zeros(5), flags=flags
    )
    d = np.zeros(5)
    d[: min(5, dist.size)] = dist.ravel()[:5]
    cam = CameraModel(
        fx=float(K[0, 0]), fy=float(K[1, 1]), skew=0.0, u0=float(K[0, 2]), v0=float(K[1, 2]),
        k1=float(d[0]), k2=float(d[1]), p1=float(d[2]), p2=float(d[3]), k3=float(d[4]),
        width=int(size[0]), height=int(size[1]),
    )  # fmt: skip
    poses = [np.concatenate([r.ravel(), t.ravel()]) for r, t in zip(rvecs, tvecs, strict=True)]
    return cam, poses, float(rms)


def _pose_T(p: FloatArray) -> FloatArray:
    """T_c_b from (rotation vector, translation)."""
    return make_T(rotvec_to_R(p[:3]), p[3:6])


class _Problem:
    """Reprojection residuals over (intrinsics, 6 pose parameters per view)."""

    def __init__(
        self,
        obj: list[FloatArray],
        img: list[FloatArray],
        size: tuple[int, int],
        keys: tuple[str, ...],
    ) -> None:
        self.obj, self.img, self.size, self.keys = obj, img, size, keys
        self.k = len(keys)
        self.counts = [len(p) for p in obj]
        self.offsets = np.concatenate([[0], np.cumsum([2 * n for n in self.counts])])
        self.steps = np.array([STEPS.get(key, DIST_STEP) for key in keys])

    def camera(self, theta: FloatArray) -> CameraModel:
        """The camera for an intrinsics vector."""
        vals = {key: float(v) for key, v in zip(self.keys, theta, strict=True)}
        return CameraModel(**vals, width=self.size[0], height=self.size[1])

    def view_residuals(self, cam: CameraModel, pose: FloatArray, i: int) -> FloatArray:
        """Predicted minus measured pixels of view i, flattened (2N,)."""
        R = rotvec_to_R(pose[:3])
        pc = self.obj[i] @ R.T + pose[3:6]
        uv, _ = cam.project(pc)
        out: FloatArray = (uv - self.img[i]).ravel()
        return out

    def residuals(self, x: FloatArray) -> FloatArray:
        """All views' residuals stacked."""
        cam = self.camera(x[: self.k])
        parts = [self.view_residuals(cam, self._pose(x, i), i) for i in range(len(self.obj))]
        return np.concatenate(parts)

    def jacobian(self, x: FloatArray, r0: FloatArray) -> FloatArray:
        """Forward differences; a view's pose columns touch only that view's rows."""
        J = np.zeros((r0.size, x.size))
        for j in range(self.k):
            xj = x.copy()
            xj[j] += self.steps[j]
            J[:, j] = (self.residuals(xj) - r0) / self.steps[j]
        cam = self.camera(x[: self.k])
        for i in range(len(self.obj)):
            lo, hi = self.offsets[i], self.offsets[i + 1]
            pose = self._pose(x, i)
            for j in range(6):
                p = pose.copy()
                p[j] += POSE_STEPS[j]
                J[lo:hi, self.k + 6 * i + j] = (
                    self.view_residuals(cam, p, i) - r0[lo:hi]
                ) / POSE_STEPS[j]
        return J

    def split(self, r: FloatArray) -> list[FloatArray]:
        """Flat residuals back into per-view (N,2) arrays."""
        return [
            r[self.offsets[i] : self.offsets[i + 1]].reshape(-1, 2) for i in range(len(self.obj))
        ]

    def _pose(self, x: FloatArray, i: int) -> FloatArray:
        return x[self.k + 6 * i : self.k + 6 * i + 6]
