"""Pose initialisation from 3D-2D pairs: the paper's DLT (eq. 9) beside OpenCV's SQPnP.

Both first remove distortion and K (skew included) with our camera model, so they solve in
normalised coordinates where the projection matrix is λ[R | t]. The DLT needs N ≥ 6 points not
all on one plane (a plane leaves the 3x4 matrix underdetermined); SQPnP accepts N ≥ 3, planar too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from host.geometry.camera import CameraModel
from host.geometry.transforms import ArrayLike, FloatArray, make_T

DLT_MIN_POINTS = 6  # 11 unknowns, 2 equations per point
SQPNP_MIN_POINTS = 3
DEGENERATE_RATIO = 1e-9  # second-smallest / largest singular value below this: no unique solution


@dataclass(frozen=True)
class PnPResult:
    """Camera pose T_c_w from a solver, with its reprojection RMS in pixels."""

    T_c_w: FloatArray
    rms_px: float
    method: str


def solve_dlt(points_w: ArrayLike, uv: ArrayLike, camera: CameraModel) -> PnPResult:
    """Paper eq. 9: Hartley-normalised DLT for the 3x4 matrix, then the pose with known K."""
    X, xn = _prepare(points_w, uv, camera, DLT_MIN_POINTS)
    T3, Xh = _normalise_3d(X)
    T2, xh = _normalise_2d(xn)
    P_hat = _dlt_matrix(Xh, xh)
    P = np.linalg.inv(T2) @ P_hat @ T3
    T_c_w = _pose_from_projection(P)
    return PnPResult(T_c_w, _rms(camera, T_c_w, X, uv), "dlt")


def solve_sqpnp(points_w: ArrayLike, uv: ArrayLike, camera: CameraModel) -> PnPResult:
    """OpenCV's SQPnP on the same normalised coordinates, same return type."""
    X, xn = _prepare(points_w, uv, camera, SQPNP_MIN_POINTS)
    ok, rvec, tvec = cv2.solvePnP(X, xn, np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError("SQPnP found no solution")
    R, _ = cv2.Rodrigues(rvec)
    T_c_w = make_T(R, tvec.ravel())
    return PnPResult(T_c_w, _rms(camera, T_c_w, X, uv), "sqpnp")


def _prepare(
    points_w: ArrayLike, uv: ArrayLike, camera: CameraModel, n_min: int
) -> tuple[FloatArray, FloatArray]:
    """Validate shapes and turn pixels into undistorted normalised coordinates."""
    X = np.ascontiguousarray(np.asarray(points_w, dtype=np.float64))
    q = np.asarray(uv, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] != 3 or q.shape != (X.shape[0], 2):
        raise ValueError(f"need points (N,3) and pixels (N,2), got {X.shape} and {q.shape}")
    if X.shape[0] < n_min:
        raise ValueError(f"need at least {n_min} point pairs, got {X.shape[0]}")
    return X, np.ascontiguousarray(camera.undistort_normalized(q))


def _normalise_3d(X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Hartley: centroid to origin, mean distance √3; returns (T, homogeneous points)."""
    c = X.mean(axis=0)
    scale = math.sqrt(3.0) / float(np.mean(np.linalg.norm(X - c, axis=1)))
    T = np.diag([scale, scale, scale, 1.0])
    T[:3, 3] = -scale * c
    return T, np.hstack([(X - c) * scale, np.ones((X.shape[0], 1))])


def _normalise_2d(x: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Hartley: centroid to origin, mean distance √2; returns (T, homogeneous points)."""
    c = x.mean(axis=0)
    scale = math.sqrt(2.0) / float(np.mean(np.linalg.norm(x - c, axis=1)))
    T = np.array([[scale, 0.0, -scale * c[0]], [0.0, scale, -scale * c[1]], [0.0, 0.0, 1.0]])
    return T, np.hstack([(x - c) * scale, np.ones((x.shape[0], 1))])


def _dlt_matrix(Xh: FloatArray, xh: FloatArray) -> FloatArray:
    """Null vector of the 2N x 12 system from eq. 9 with the denominator cleared."""
    n = Xh.shape[0]
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xh[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xh[:, 1:2] * Xh
    _, S, Vt = np.linalg.svd(A)
    if S[-2] < DEGENERATE_RATIO * S[0]:
        raise ValueError("DLT is degenerate: points coplanar or collinear (use solve_sqpnp)")
    out: FloatArray = Vt[-1].reshape(3, 4)
    return out


def _pose_from_projection(P: FloatArray) -> FloatArray:
    """λ[R | t] → T_c_w: fix the sign by det, the scale by singular values, R by SVD."""
    M = P[:, :3]
    if np.linalg.det(M) < 0.0:
        P = -P
        M = -M
    U, S, Vt = np.linalg.svd(M)
    R = U @ Vt
    t = P[:, 3] / float(np.mean(S))
    return make_T(R, t)


def _rms(camera: CameraModel, T_c_w: FloatArray, X: FloatArray, uv: ArrayLike) -> float:
    """Root-mean-square reprojection error in pixels (inf if a point falls behind)."""
    pred, valid = camera.project_world(T_c_w, X)
    if not np.all(valid):
        return math.inf
    d = pred - np.asarray(uv, dtype=np.float64)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))
