"""Pan/tilt head (paper eq. 10), camera-to-head matrix M_cr (eq. 14) and the kinematic chain.

T_w_c = T_w_t(s) · T_t_r · R_head(pan, tilt) · M_cr, with M_cr = T_r_c (camera points into the
head frame r, as eq. 10 applies it to camera points).

Head axes: the paper's text (§3.1.1, item 5) says the head turns about Z_r and Y_r, while eq. 10's
matrix is Ry(β)·Rx(α). We follow the text: R_head = Rz(pan) · Ry(tilt). Reasons: the frame
definition is the text; a pan/tilt head's outer axis is vertical, and with the trolley frame's z
pointing down (track.py) that axis is Z_r; eq. 10 reads as eq. 3 with γ = 0 and serves only the
error analysis of §5.1. `head_rotation` is the one place that encodes this choice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from host.geometry.track import Track, runway
from host.geometry.transforms import (
    ArrayLike,
    FloatArray,
    invert_T,
    make_T,
    nearest_rotation,
    rot_y,
    rot_z,
)

# Paper eq. 14 as printed (mm). Its 3x3 block is not orthonormal (rows 1 and 2 meet at 90.24°,
# singular values 1.0029/0.9991/0.9983), so M_CR_DEFAULT is its nearest rotation (SVD).
M_CR_PAPER = np.array(
    [
        [0.9907, 0.1353, -0.0064, 50.843],
        [-0.1396, 0.9915, 0.0093, 47.094],
        [0.0083, -0.0085, 0.9990, 76.177],
        [0.0, 0.0, 0.0, 1.0],
    ]
)
AIM_ITERATIONS = 4  # fixed-point passes in aim(); the camera offset is ~0.1 m against metres


# Largest |σ - 1| of a rotation block accepted as rounding of printed figures: eq. 14 as printed
# is off by 0.0029; a wrong matrix (a scale, a zero block, a shear) is off by far more.
ORTHONORMAL_TOLERANCE = 0.01


@dataclass(frozen=True)
class Orthonormalisation:
    """What making a transform's rotation block orthonormal changed."""

    singular_values: tuple[float, float, float]
    max_change: float  # largest change of one entry of the 3x3 block

    def describe(self) -> str:
        """One line for logs and `orbitar config check`."""
        sv = "/".join(f"{s:.4f}" for s in self.singular_values)
        moved = f"{self.max_change:.4f}"
        return f"rotation orthonormalised (singular values {sv}, entries moved by up to {moved})"


def rotation_problem(T: ArrayLike, tolerance: float = ORTHONORMAL_TOLERANCE) -> str | None:
    """Why the 3x3 block of a 4x4 transform is no rotation; None when it is one within tolerance."""
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    if not np.all(np.isfinite(R)):
        return "the rotation block must be finite"
    sv = np.linalg.svd(R, compute_uv=False)
    deviation = float(np.max(np.abs(sv - 1.0)))
    if deviation > tolerance:
        shown = "/".join(f"{s:.4g}" for s in sv)
        return (
            f"the rotation block is not a rotation: singular values {shown}, off by "
            f"{deviation:.4g} (a rotation has 1/1/1; up to {tolerance:g} is accepted as rounding)"
        )
    det = float(np.linalg.det(R))
    if det < 0:
        return f"the rotation block is a reflection (determinant {det:.4f}), not a rotation"
    return None


def orthonormalisation(T: ArrayLike) -> Orthonormalisation:
    """How far the rotation block of T is from the rotation orthonormalize_T puts in its place."""
    T_ = np.asarray(T, dtype=np.float64)
    R = T_[:3, :3]
    sv = np.linalg.svd(R, compute_uv=False)
    change = float(np.max(np.abs(nearest_rotation(R) - R)))
    return Orthonormalisation((float(sv[0]), float(sv[1]), float(sv[2])), change)


def orthonormalize_T(T: ArrayLike, tolerance: float = ORTHONORMAL_TOLERANCE) -> FloatArray:
    """Replace the rotation block of a 4x4 transform by its nearest rotation.

    ValueError (saying why) when the block is no rotation within `tolerance`: a scale, a zero
    block or a reflection is a wrong matrix, not a rounded one, and must not be silently fixed.
    """
    T_ = np.asarray(T, dtype=np.float64)
    problem = rotation_problem(T_, tolerance)
    if problem is not None:
        raise ValueError(problem)
    return make_T(nearest_rotation(T_[..., :3, :3]), T_[..., :3, 3])


M_CR_DEFAULT = orthonormalize_T(M_CR_PAPER)


def head_rotation(pan_rad: ArrayLike, tilt_rad: ArrayLike) -> FloatArray:
    """T_r0_r: head rotation Rz(pan) · Ry(tilt) as 4x4 (pan is the outer axis)."""
    R = rot_z(pan_rad) @ rot_y(tilt_rad)
    return make_T(R, np.zeros(R.shape[:-1]))


def _default_T_r_c() -> FloatArray:
    return M_CR_DEFAULT.copy()


@dataclass(frozen=True, eq=False)
class Rig:
    """Kinematic parameters: track, head mount on the trolley (T_t_r), M_cr (T_r_c) and the
    rangefinder's mount in the head frame (T_r_l; its beam runs along +z_l)."""

    track: Track = field(default_factory=runway)
    T_t_r: FloatArray = field(default_factory=lambda: np.eye(4))
    T_r_c: FloatArray = field(default_factory=_default_T_r_c)
    T_r_l: FloatArray = field(default_factory=lambda: np.eye(4))

    def T_w_r(self, s_mm: ArrayLike, pan_rad: ArrayLike, tilt_rad: ArrayLike) -> FloatArray:
        """Head frame in the world after the head has turned, broadcast over inputs."""
        out: FloatArray = self.track.pose(s_mm) @ self.T_t_r @ head_rotation(pan_rad, tilt_rad)
        return out

    def T_w_c(self, s_mm: ArrayLike, pan_rad: ArrayLike, tilt_rad: ArrayLike) -> FloatArray:
        """Camera pose in the world for arc length s and head angles."""
        out: FloatArray = self.T_w_r(s_mm, pan_rad, tilt_rad) @ self.T_r_c
        return out

    def T_c_w(self, s_mm: ArrayLike, pan_rad: ArrayLike, tilt_rad: ArrayLike) -> FloatArray:
        """World-to-camera transform (the extrinsics used for projection)."""
        return invert_T(self.T_w_c(s_mm, pan_rad, tilt_rad))

    def aim(self, s_mm: float, target_w: ArrayLike) -> tuple[float, float]:
        """Head angles (pan, tilt) that put a world point on the optical axis, tilt near 0."""
        target = np.asarray(target_w, dtype=np.float64)
        T_w_r0 = self.track.pose(s_mm) @ self.T_t_r
        axis_r = self.T_r_c[:3, 2]
        pan = tilt = 0.0
        for _ in range(AIM_ITERATIONS):
            origin_w = self.T_w_c(s_mm, pan, tilt)[:3, 3]
            d_w = target - origin_w
            d_r0 = T_w_r0[:3, :3].T @ (d_w / np.linalg.norm(d_w))
            pan, tilt = _solve_pan_tilt(axis_r, d_r0)
        return pan, tilt


def _solve_pan_tilt(a: FloatArray, d: FloatArray) -> tuple[float, float]:
    """Angles with Rz(pan) Ry(tilt) a = d for unit vectors a, d (the smaller head excursion)."""
    # Rz keeps z, so tilt alone must match d_z: a_z cos t - a_x sin t = d_z. Of the two tilts,
    # take the one whose pair needs the smaller largest angle: least slewing, furthest from stops.
    amp = math.hypot(a[2], a[0])
    base = math.atan2(-a[0], a[2])
    spread = math.acos(max(-1.0, min(1.0, d[2] / amp)))
    pairs = []
    for tilt in (base + spread, base - spread):
        v = rot_y(tilt) @ a
        pan = math.atan2(d[1], d[0]) - math.atan2(v[1], v[0])
        pairs.append((math.remainder(pan, math.tau), math.remainder(tilt, math.tau)))
    return min(pairs, key=lambda p: max(abs(p[0]), abs(p[1])))
