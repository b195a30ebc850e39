"""Camera-to-head M_cr and track-to-world placement from views of a fixed calibration target.

Each view is taken at a known arc length s and head angles and sees a fixed target (chessboard
frame b). With k the track frame, the chain T_k_r(s, pan, tilt) = T_k_t(s) · T_t_r · R_head is
known, and for every view

    T_c_b = M_cr⁻¹ · T_k_r⁻¹ · T_b_k⁻¹        (robot-world hand-eye: A X = Z B)

with two unknowns: M_cr = T_r_c and T_b_k (where the track lies in the target frame). OpenCV's
calibrateRobotWorldHandEye (Shah's method) gives a closed-form start from per-view PnP poses; a
Levenberg-Marquardt pass on the reprojection error of all target points then refines both, as
the closed form weighs rotation and translation arbitrarily (host.calibration.lsq, which also
gives the 12×12 covariance of both transforms as local perturbations T·exp(δ), δ = (ω, t)).
T_w_track = T_w_b · T_b_k, its covariance adding the surveyed board pose's.
T_t_r (head mount on the trolley) is taken as known: it is not separable from M_cr and T_b_k with
a head whose axes are the only source of rotation on a straight.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from host.calibration import lsq
from host.geometry.camera import CameraModel
from host.geometry.head import head_rotation
from host.geometry.pnp import solve_sqpnp
from host.geometry.track import Track
from host.geometry.transforms import (
    ArrayLike,
    FloatArray,
    invert_T,
    make_T,
    rotation_angle,
    rotvec_to_R,
)

MIN_VIEWS = 3
LM_STEP = 1e-6  # finite-difference step for the Jacobian (rad and mm)
HEAD_STEP = 1e-6  # rad, for the head angles' share


@dataclass(frozen=True)
class HandEyeView:
    """One observation: joint values and target points (N,3, frame b) seen at pixels (N,2)."""

    s_mm: float
    pan_rad: float
    tilt_rad: float
    object_points: FloatArray
    image_points: FloatArray
    # σ of the head angles as this view took them (a rest's median reads better than one
    # reading: commissioning.head_noise.rest_sigma); 0: taken as exact
    head_sigma_rad: float = 0.0


@dataclass(frozen=True)
class HandEyeResult:
    """Estimated M_cr and track placement, their covariances, residuals before and after."""

    M_cr: FloatArray  # T_r_c
    T_b_track: FloatArray
    T_w_track: FloatArray
    rms_px: float  # reprojection RMS after refinement
    initial_rms_px: float  # reprojection RMS of the closed-form (OpenCV) solution
    rotation_residual_rad: FloatArray  # per view, predicted vs PnP camera pose
    translation_residual_mm: FloatArray
    covariance: FloatArray  # 12×12 over (δ M_cr, δ T_b_track), local (ω rad, t mm)
    track_covariance: FloatArray  # 6×6 of T_w_track, the board survey's included
    per_view_rms_px: FloatArray
    residuals_px: list[FloatArray]
    # Cov(δ(M_cr, T_b_track), δθ), 12×10, and the camera covariance Σθ it came from: the fit
    # moves with the camera's error (None when no camera covariance was given); T_w_track's
    # is T_b_track's, the board survey being independent of the camera
    camera_cross: FloatArray | None = None
    camera_cov: FloatArray | None = None
    # Cov(δ(M_cr, T_b_track), δ zero), 12: the fit moves with the zero the views' arc lengths
    # were counted from (on a straight the placement takes it up); None without a zero's σ
    home_cross: FloatArray | None = None

    @property
    def cov_M_cr(self) -> FloatArray:
        """6×6 local covariance of M_cr."""
        return np.asarray(self.covariance[:6, :6], dtype=np.float64)

    def sigma(
        self, cov: FloatArray
    ) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(σ rotation rad ×3, σ translation mm ×3) of a 6×6 local covariance."""
        d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        return (float(d[0]), float(d[1]), float(d[2])), (float(d[3]), float(d[4]), float(d[5]))


def calibrate_handeye(
    views: Sequence[HandEyeView],
    track: Track,
    camera: CameraModel,
    T_t_r: ArrayLike | None = None,
    T_w_b: ArrayLike | None = None,
    cov_T_w_b: ArrayLike | None = None,
    camera_cov: ArrayLike | None = None,
    home_sigma_mm: float = 0.0,
) -> HandEyeResult:
    """Solve M_cr and T_w_track; T_w_b is the target's surveyed world pose (default: world = b).

    `camera_cov` (10×10 over CAMERA_KEYS, e.g. from the intrinsics calibration) adds the
    camera's own uncertainty to the result's: a focal length off by 0.1 % moves the camera by
    0.1 % of the board distance, far more than the pixel noise does. Each view's
    `head_sigma_rad` (its head angles' error) adds theirs: it turns a whole view at once, so
    with tens of corners a view it can outweigh the pixel noise in M_cr's rotation.
    `home_sigma_mm` (the σ of the controller's zero the views' arc lengths were computed with)
    adds that of the arc lengths: on a straight a home error and a shift of the track along it
    are one and the same, so the fit puts the home's error into the track placement.
    """
    if len(views) < MIN_VIEWS:
        raise ValueError(f"need at least {MIN_VIEWS} views, got {len(views)}")
    mount = np.eye(4) if T_t_r is None else np.asarray(T_t_r, dtype=np.float64)
    T_k_r = [track.local_pose(v.s_mm) @ mount @ head_rotation(v.pan_rad, v.tilt_rad) for v in views]
    T_c_b = [solve_sqpnp(v.object_points, v.image_points, camera).T_c_w for v in views]
    M_cr0, T_b_k0 = _closed_form(T_c_b, T_k_r)
    problem = _Problem(views, T_k_r, camera)
    initial = problem.rms(M_cr0, T_b_k0)
    M_cr, T_b_k = problem.refine(M_cr0, T_b_k0)
    r = problem.residuals(M_cr, T_b_k)
    J = problem.jacobian(M_cr, T_b_k, r)
    cov = lsq.covariance(J, r)  # linearised at the solution, in its own local frame
    cam_cov = cross = None
    if camera_cov is not None:
        cam_cov = np.asarray(camera_cov, dtype=np.float64)
        A = _camera_term(problem, M_cr, T_b_k, J, cam_cov)
        cov, cross = cov + A @ cam_cov @ A.T, A @ cam_cov
    head_var = np.repeat([v.head_sigma_rad**2 for v in views], 2)  # pan, tilt per view
    if head_var.any():
        A_h = _head_term(problem, views, track, mount, M_cr, T_b_k, J)
        cov = cov + (A_h * head_var) @ A_h.T
    home_cross = None
    if home_sigma_mm > 0.0:
        A_s = _home_term(views, track, mount, problem, M_cr, T_b_k, J)
        cov, home_cross = cov + home_sigma_mm**2 * np.outer(A_s, A_s), home_sigma_mm**2 * A_s
    rot_res, trans_res = _pose_residuals(M_cr, T_b_k, T_k_r, T_c_b)
    T_wb = np.eye(4) if T_w_b is None else np.asarray(T_w_b, dtype=np.float64)
    cov_wb = np.zeros((6, 6)) if cov_T_w_b is None else np.asarray(cov_T_w_b, dtype=np.float64)
    Ad = adjoint(invert_T(T_b_k))  # δ of T_w_b seen in T_w_track's local frame
    cov_wk = Ad @ cov_wb @ Ad.T + cov[6:, 6:]
    per_view = problem.split(r)
    rms_v = np.array([float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) for e in per_view])
    return HandEyeResult(
        M_cr, T_b_k, T_wb @ T_b_k, problem.rms(M_cr, T_b_k), initial, rot_res, trans_res,
        cov, cov_wk, rms_v, per_view, cross, cam_cov, home_cross,
    )  # fmt: skip


CAMERA_KEYS = ("fx", "fy", "skew", "u0", "v0", "k1", "k2", "p1", "p2", "k3")
CAMERA_STEPS = (1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7, 1e-7, 1e-7)


def _camera_term(
    problem: _Problem, M_cr: FloatArray, T_b_k: FloatArray, J: FloatArray, cam_cov: FloatArray
) -> FloatArray:
    """How the fit moves with the camera's error: δx = A δθ, A = −(JᵀJ)⁻¹Jᵀ J_θ."""
    base = problem.camera
    r0 = problem.residuals(M_cr, T_b_k)
    J_theta = np.zeros((r0.size, len(CAMERA_KEYS)))
    for j, (key, step) in enumerate(zip(CAMERA_KEYS, CAMERA_STEPS, strict=True)):
        if cam_cov[j, j] <= 0.0:
            continue
        problem.camera = dataclasses.replace(base, **{key: getattr(base, key) + step})
        J_theta[:, j] = (problem.residuals(M_cr, T_b_k) - r0) / step
    problem.camera = base
    out: FloatArray = -np.linalg.pinv(J.T @ J) @ J.T @ J_theta
    return out


def _head_term(
    problem: _Problem, views: Sequence[HandEyeView], track: Track, mount: FloatArray,
    M_cr: FloatArray, T_b_k: FloatArray, J: FloatArray,
) -> FloatArray:  # fmt: skip
    """How the fit moves with each view's head angles: δx = A_h δh, δh = (pan, tilt) per view."""
    r0 = problem.residuals(M_cr, T_b_k)
    J_h = np.zeros((r0.size, 2 * len(views)))
    for i, v in enumerate(views):
        saved = problem.T_r_k[i]
        for j, (dp, dt) in enumerate(((HEAD_STEP, 0.0), (0.0, HEAD_STEP))):
            T = track.local_pose(v.s_mm) @ mount @ head_rotation(v.pan_rad + dp, v.tilt_rad + dt)
            problem.T_r_k[i] = invert_T(T)
            J_h[:, 2 * i + j] = (problem.residuals(M_cr, T_b_k) - r0) / HEAD_STEP
        problem.T_r_k[i] = saved
    out: FloatArray = -np.linalg.pinv(J.T @ J) @ J.T @ J_h
    return out


def _home_term(
    views: Sequence[HandEyeView], track: Track, mount: FloatArray, problem: _Problem,
    M_cr: FloatArray, T_b_k: FloatArray, J: FloatArray,
) -> FloatArray:  # fmt: skip
    """How the fit moves with a common error of every view's arc length (the zero's): δx =
    A_s δs, (12,)."""
    step = 1.0
    shifted = [
        track.local_pose(v.s_mm + step) @ mount @ head_rotation(v.pan_rad, v.tilt_rad)
        for v in views
    ]
    moved = _Problem(views, shifted, problem.camera)
    J_s = (moved.residuals(M_cr, T_b_k) - problem.residuals(M_cr, T_b_k)) / step
    out: FloatArray = -np.linalg.pinv(J.T @ J) @ J.T @ J_s
    return out


def adjoint(T: FloatArray) -> FloatArray:
    """6×6 adjoint of T = (R, p) on local perturbations (ω, t): T·exp(δ)·T⁻¹ = exp(Ad δ).

    A·exp(δ)·B = A·B·exp(Ad(B⁻¹) δ), so a perturbation of a left factor moves to the right end.
    """
    R, p = T[:3, :3], T[:3, 3]
    px = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    out = np.zeros((6, 6))
    out[:3, :3] = R
    out[3:, 3:] = R
    out[3:, :3] = px @ R
    return out


def _closed_form(T_c_b: list[FloatArray], T_k_r: list[FloatArray]) -> tuple[FloatArray, FloatArray]:
    """OpenCV robot-world hand-eye: world = target b, base = track k, gripper = head r."""
    T_r_k = [invert_T(T) for T in T_k_r]
    R_b2g, t_b2g, R_w2c, t_w2c = _split(T_r_k) + _split(T_c_b)
    R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(
        R_w2c, t_w2c, R_b2g, t_b2g, method=cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH
    )
    T_b_k = make_T(R_bw, np.ravel(t_bw))  # base2world maps track points into the target frame
    M_cr = invert_T(make_T(R_gc, np.ravel(t_gc)))  # gripper2cam is T_c_r
    return M_cr, T_b_k


def _split(Ts: list[FloatArray]) -> tuple[list[FloatArray], list[FloatArray]]:
    """Rotations and (3,1) translations as OpenCV's list arguments."""
    return [T[:3, :3].copy() for T in Ts], [T[:3, 3:4].copy() for T in Ts]


def _perturb(T: FloatArray, d: FloatArray) -> FloatArray:
    """Right-multiplied local update T · exp(d) with d = (rotation vector, translation)."""
    out: FloatArray = T @ make_T(rotvec_to_R(d[:3]), d[3:])
    return out


class _Problem:
    """Reprojection least squares over (M_cr, T_b_k), 12 local parameters."""

    def __init__(self, views: Sequence[HandEyeView], T_k_r: list[FloatArray], camera: CameraModel):
        self.camera = camera
        self.T_r_k = [invert_T(T) for T in T_k_r]
        self.X = [np.asarray(v.object_points, dtype=np.float64) for v in views]
        self.uv = np.concatenate([np.asarray(v.image_points, dtype=np.float64) for v in views])
        self.offsets = np.concatenate([[0], np.cumsum([2 * len(x) for x in self.X])])

    def residuals(self, M_cr: FloatArray, T_b_k: FloatArray) -> FloatArray:
        """Stacked pixel residuals of all views (2·ΣN,)."""
        T_c_r, T_k_b = invert_T(M_cr), invert_T(T_b_k)
        pred = [
            self.camera.project_world(T_c_r @ T_r_k @ T_k_b, X)[0]
            for T_r_k, X in zip(self.T_r_k, self.X, strict=True)
        ]
        out: FloatArray = (np.concatenate(pred) - self.uv).ravel()
        return out

    def rms(self, M_cr: FloatArray, T_b_k: FloatArray) -> float:
        """Reprojection RMS in pixels (per point, both axes together)."""
        r = self.residuals(M_cr, T_b_k)
        return float(np.sqrt(2.0 * np.mean(r * r)))

    def refine(self, M_cr: FloatArray, T_b_k: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Levenberg-Marquardt in local coordinates around the closed-form start."""

        def fn(x: FloatArray) -> FloatArray:
            return self.residuals(_perturb(M_cr, x[:6]), _perturb(T_b_k, x[6:]))

        sol = lsq.solve(fn, np.zeros(12), lsq.forward_jacobian(fn, np.full(12, LM_STEP)))
        return _perturb(M_cr, sol.x[:6]), _perturb(T_b_k, sol.x[6:])

    def jacobian(self, M_cr: FloatArray, T_b_k: FloatArray, r0: FloatArray) -> FloatArray:
        """Forward differences over the 12 local parameters at (M_cr, T_b_k)."""

        def fn(x: FloatArray) -> FloatArray:
            return self.residuals(_perturb(M_cr, x[:6]), _perturb(T_b_k, x[6:]))

        return lsq.forward_jacobian(fn, np.full(12, LM_STEP))(np.zeros(12), r0)

    def split(self, r: FloatArray) -> list[FloatArray]:
        """Flat residuals back into per-view (N,2) arrays."""
        return [r[self.offsets[i] : self.offsets[i + 1]].reshape(-1, 2) for i in range(len(self.X))]


def _pose_residuals(
    M_cr: FloatArray, T_b_k: FloatArray, T_k_r: list[FloatArray], T_c_b: list[FloatArray]
) -> tuple[FloatArray, FloatArray]:
    """Per view: angle and distance between predicted and PnP target poses in the camera."""
    pred = np.stack([invert_T(M_cr) @ invert_T(T) @ invert_T(T_b_k) for T in T_k_r])
    obs = np.stack(T_c_b)
    dR = np.swapaxes(pred[:, :3, :3], 1, 2) @ obs[:, :3, :3]
    return rotation_angle(dR), np.linalg.norm(pred[:, :3, 3] - obs[:, :3, 3], axis=1)
