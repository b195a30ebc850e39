"""Camera-to-head M_cr and track-to-world placement from views of a fixed calibration target.

Each view is taken at a known arc length s and head angles and sees a fixed target (chessboard
frame b). With k the track frame, the chain T_k_r(s, pan, tilt) = T_k_t(s) · T_t_r · R_head is
known, and for every view

    T_c_b = M_cr⁻¹ · T_k_r⁻¹ · T_b_k⁻¹        (robot-world hand-eye: A X = Z B)

with two unknowns: M_cr = T_r_c and T_b_k (where the track lies in the target frame). OpenCV's
calibrateRobotWorldHandEye (Shah's method) gives a closed-form start from per-view PnP poses; a
Levenberg-Marquardt pass on the reprojection error of all target points then refines both, as
the closed form weighs rotation and translation arbitrarily. T_w_track = T_w_b · T_b_k.
T_t_r (head mount on the trolley) is taken as known: it is not separable from M_cr and T_b_k with
a head whose axes are the only source of rotation on a straight.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

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
LM_ITERATIONS = 50
LM_STEP = 1e-6  # finite-difference step for the Jacobian (rad and mm)
LM_LAMBDA0 = 1e-3
LM_TOL = 1e-10  # relative cost decrease at which LM stops


@dataclass(frozen=True)
class HandEyeView:
    """One observation: joint values and target points (N,3, frame b) seen at pixels (N,2)."""

    s_mm: float
    pan_rad: float
    tilt_rad: float
    object_points: FloatArray
    image_points: FloatArray


@dataclass(frozen=True)
class HandEyeResult:
    """Estimated M_cr and track placement, with residuals before and after refinement."""

    M_cr: FloatArray  # T_r_c
    T_b_track: FloatArray
    T_w_track: FloatArray
    rms_px: float  # reprojection RMS after refinement
    initial_rms_px: float  # reprojection RMS of the closed-form (OpenCV) solution
    rotation_residual_rad: FloatArray  # per view, predicted vs PnP camera pose
    translation_residual_mm: FloatArray

    def to_config(self) -> dict[str, object]:
        """{"head": {"m_cr": 4x4}, "track": {"T_w_track": 4x4}} as nested lists."""
        return {
            "head": {"m_cr": self.M_cr.tolist()},
            "track": {"T_w_track": self.T_w_track.tolist()},
        }


def calibrate_handeye(
    views: Sequence[HandEyeView],
    track: Track,
    camera: CameraModel,
    T_t_r: ArrayLike | None = None,
    T_w_b: ArrayLike | None = None,
) -> HandEyeResult:
    """Solve M_cr and T_w_track; T_w_b is the target's world pose (default: world = target)."""
    if len(views) < MIN_VIEWS:
        raise ValueError(f"need at least {MIN_VIEWS} views, got {len(views)}")
    mount = np.eye(4) if T_t_r is None else np.asarray(T_t_r, dtype=np.float64)
    T_k_r = [track.local_pose(v.s_mm) @ mount @ head_rotation(v.pan_rad, v.tilt_rad) for v in views]
    T_c_b = [solve_sqpnp(v.object_points, v.image_points, camera).T_c_w for v in views]
    M_cr0, T_b_k0 = _closed_form(T_c_b, T_k_r)
    problem = _Problem(views, T_k_r, camera)
    initial = problem.rms(M_cr0, T_b_k0)
    M_cr, T_b_k = problem.refine(M_cr0, T_b_k0)
    rot_res, trans_res = _pose_residuals(M_cr, T_b_k, T_k_r, T_c_b)
    T_wb = np.eye(4) if T_w_b is None else np.asarray(T_w_b, dtype=np.float64)
    return HandEyeResult(
        M_cr, T_b_k, T_wb @ T_b_k, problem.rms(M_cr, T_b_k), initial, rot_res, trans_res
    )


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
        """Levenberg-Marquardt with a forward-difference Jacobian in local coordinates."""
        r = self.residuals(M_cr, T_b_k)
        cost, lam = float(r @ r), LM_LAMBDA0
        for _ in range(LM_ITERATIONS):
            J = self._jacobian(M_cr, T_b_k, r)
            H, g = J.T @ J, J.T @ r
            d = np.asarray(np.linalg.solve(H + lam * np.diag(np.diag(H)), -g), dtype=np.float64)
            M_new, T_new = _perturb(M_cr, d[:6]), _perturb(T_b_k, d[6:])
            r_new = self.residuals(M_new, T_new)
            c_new = float(r_new @ r_new)
            if c_new < cost:
                done = cost - c_new < LM_TOL * cost
                M_cr, T_b_k, r, cost, lam = M_new, T_new, r_new, c_new, lam * 0.3
                if done:
                    break
            else:
                lam *= 10.0
        return M_cr, T_b_k

    def _jacobian(self, M_cr: FloatArray, T_b_k: FloatArray, r0: FloatArray) -> FloatArray:
        """Forward differences over the 12 local parameters."""
        J = np.empty((r0.size, 12))
        for j in range(12):
            d = np.zeros(12)
            d[j] = LM_STEP
            rj = self.residuals(_perturb(M_cr, d[:6]), _perturb(T_b_k, d[6:]))
            J[:, j] = (rj - r0) / LM_STEP
        return J


def _pose_residuals(
    M_cr: FloatArray, T_b_k: FloatArray, T_k_r: list[FloatArray], T_c_b: list[FloatArray]
) -> tuple[FloatArray, FloatArray]:
    """Per view: angle and distance between predicted and PnP target poses in the camera."""
    pred = np.stack([invert_T(M_cr) @ invert_T(T) @ invert_T(T_b_k) for T in T_k_r])
    obs = np.stack(T_c_b)
    dR = np.swapaxes(pred[:, :3, :3], 1, 2) @ obs[:, :3, :3]
    return rotation_angle(dR), np.linalg.norm(pred[:, :3, 3] - obs[:, :3, 3], axis=1)
