"""The workpiece frame from surveyed feature points, with its covariance (`survey workpiece`).

Three points: the paper's definition (§3.1.1; host.geometry.workpiece): origin P1, Z along
P1→P5, Y in the plane of P1, P3, P5. More points, with the model's own coordinates of the same
features: the rigid transform that best maps the model's points onto the measured ones (Kabsch,
least squares), with per-point residuals. Either way the 6×6 covariance of T_w_p, as the rig
file keeps it (local perturbation T·exp(δ), δ = (ω, t)), follows from the measured points' σ:
through the fit's Jacobian for least squares, by differentiating the paper's construction for
three points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from host.geometry.transforms import ArrayLike, FloatArray, make_T, rotvec_to_R
from host.geometry.workpiece import workpiece_frame

DIFF_MM = 1e-4
MIN_FIT_POINTS = 3


@dataclass(frozen=True)
class WorkpieceFit:
    """T_w_p, its 6×6 local covariance, and the residual of each measured point (mm)."""

    T_w_p: FloatArray
    covariance: FloatArray
    residuals_mm: FloatArray  # (N,) distance between measured and fitted point (0 for 3 points)

    @property
    def rms_mm(self) -> float:
        """RMS of the residuals."""
        return float(np.sqrt(np.mean(self.residuals_mm**2))) if self.residuals_mm.size else 0.0


def frame_from_three(p1: ArrayLike, p3: ArrayLike, p5: ArrayLike, sigma_mm: float) -> WorkpieceFit:
    """The paper's frame from P1, P3, P5, each measured with isotropic σ (mm)."""
    P = np.array([p1, p3, p5], dtype=np.float64)
    T = workpiece_frame(P[0], P[1], P[2])
    J = np.zeros((6, 9))
    for k in range(9):
        Q = P.copy().ravel()
        Q[k] += DIFF_MM
        Qm = Q.reshape(3, 3)
        J[:, k] = _local(T, workpiece_frame(Qm[0], Qm[1], Qm[2])) / DIFF_MM
    cov = (sigma_mm**2) * (J @ J.T)
    return WorkpieceFit(T, cov, np.zeros(3))


def fit_frame(measured_w: ArrayLike, model_p: ArrayLike, sigma_mm: float) -> WorkpieceFit:
    """Least-squares T_w_p with T_w_p · model_p ≈ measured_w (rows are the same features)."""
    Y = np.asarray(measured_w, dtype=np.float64).reshape(-1, 3)
    X = np.asarray(model_p, dtype=np.float64).reshape(-1, 3)
    if len(Y) != len(X) or len(Y) < MIN_FIT_POINTS:
        got = f"got {len(Y)} and {len(X)}"
        raise ValueError(f"need ≥ {MIN_FIT_POINTS} measured points matching the model's, {got}")
    cx, cy = X.mean(axis=0), Y.mean(axis=0)
    U, _, Vt = np.linalg.svd((X - cx).T @ (Y - cy))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    R = Vt.T @ D @ U.T
    if np.linalg.matrix_rank(X - cx, tol=1e-6) < 2:
        raise ValueError("the model's points are collinear: the workpiece frame is undefined")
    T = make_T(R, cy - R @ cx)
    fitted = X @ R.T + T[:3, 3]
    res = np.linalg.norm(Y - fitted, axis=1)
    # r_i(δ) = T·exp(δ)·X_i − Y_i: ∂/∂ω = −R [X_i]×, ∂/∂t = R
    J = np.zeros((3 * len(X), 6))
    for i, x in enumerate(X):
        J[3 * i : 3 * i + 3, :3] = -R @ _cross(x)
        J[3 * i : 3 * i + 3, 3:] = R
    cov = np.asarray((sigma_mm**2) * np.linalg.inv(J.T @ J), dtype=np.float64)
    return WorkpieceFit(T, cov, res)


def _cross(v: FloatArray) -> FloatArray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _local(T: FloatArray, T2: FloatArray) -> FloatArray:
    """δ with T2 = T · exp(δ) (first order)."""
    d = np.linalg.inv(T) @ T2
    R = d[:3, :3]
    w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return np.concatenate([w, d[:3, 3]])


def exp_local(T: FloatArray, d: FloatArray) -> FloatArray:
    """T · exp(δ) (the rig file's perturbation convention)."""
    out: FloatArray = T @ make_T(rotvec_to_R(d[:3]), d[3:6])
    return out
