"""A rangefinder reading as a function of the rig's calibrated blocks, for fits and their σ.

The host predicts a reading with `host.geometry.rangefinder` (the beam cast into the surveyed
scene). A fit, or the σ of a quantity solved from a reading, needs that prediction as a smooth
function of the blocks that carry uncertainty: the mount T_r_l and the track's placement
T_w_track (each moved by a local perturbation T · exp(δ), the rig schema's convention), the
trolley's arc length and each surveyed surface's offset along its normal. Readings keep the
surface the calibrated rig's beam met, so the function has no jumps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from host.geometry.head import Rig
from host.geometry.rangefinder import PARALLEL_COS, RangeScene
from host.geometry.transforms import ArrayLike, FloatArray, make_T, rotvec_to_R
from host.rig import RigSpec, build_kinematics, build_scene

MIN_COS_INCIDENCE = 0.3  # a beam within ~73° of the surface normal: a clean spot
MIN_CLEARANCE_MM = 300.0  # the next surface along the beam this much further: not a corner
DIFF_STEPS = np.array([1e-6] * 3 + [1e-3] * 3)  # central differences over (ω [rad], t [mm])


def local(T: FloatArray, delta: Sequence[float] | FloatArray) -> FloatArray:
    """T · exp(δ) for δ = (ωx, ωy, ωz, tx, ty, tz) (the schema's local perturbation)."""
    d = np.asarray(delta, dtype=np.float64)
    return T @ make_T(rotvec_to_R(d[:3]), d[3:])


@dataclass(frozen=True)
class Hall:
    """The surveyed surfaces as arrays: points, unit normals, survey σ along each normal."""

    scene: RangeScene
    points: FloatArray
    normals: FloatArray
    sigma_mm: FloatArray

    @classmethod
    def of(cls, spec: RigSpec) -> Hall | None:
        """The rig file's hall (None when it lists no surfaces)."""
        scene = build_scene(spec)
        if scene is None:
            return None
        return cls(
            scene,
            np.array([s.point_w for s in scene.surfaces]),
            np.array([s.normal_w for s in scene.surfaces]),
            np.array([s.sigma_mm for s in spec.hall.surfaces]),
        )


@dataclass(frozen=True)
class Poses:
    """Where each reading was taken (track arc length, head angles) and the surface it met."""

    s_mm: FloatArray
    pan_rad: FloatArray
    tilt_rad: FloatArray
    surface: np.ndarray  # index into Hall

    def __len__(self) -> int:
        return len(self.s_mm)


def clean_hits(
    rig: Rig, hall: Hall, s_mm: ArrayLike, pan_rad: ArrayLike, tilt_rad: ArrayLike
) -> np.ndarray:
    """For each pose, the surface its reading would measure, or -1 when that is ambiguous
    (no surface, a grazing beam, another surface close behind: a corner). Vectorised
    RangeScene.cast over poses."""
    T = rig.T_w_r(np.asarray(s_mm, dtype=np.float64), pan_rad, tilt_rad) @ rig.T_r_l
    o, z = T[..., :3, 3].reshape(-1, 3), T[..., :3, 2].reshape(-1, 3)
    cos = z @ hall.normals.T  # (poses, surfaces)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("jk,ijk->ij", hall.normals, hall.points[None] - o[:, None]) / cos
    t = np.where((np.abs(cos) > PARALLEL_COS) & (t > 0.0), t, np.inf)
    radius = np.array([s.radius_mm for s in hall.scene.surfaces])
    if np.isfinite(radius).any():  # patches: a hit outside the radius misses
        spot = o[:, None] + np.where(np.isfinite(t), t, 0.0)[..., None] * z[:, None]
        far = np.linalg.norm(spot - hall.points[None], axis=-1) > radius
        t = np.where(far, np.inf, t)
    order = np.sort(t, axis=1)
    first = np.argmin(t, axis=1)
    nearest = order[:, 0]
    behind = order[:, 1] if t.shape[1] > 1 else np.full(len(t), np.inf)
    incidence = np.abs(cos[np.arange(len(t)), first])
    ok = np.isfinite(nearest) & (incidence >= MIN_COS_INCIDENCE)
    ok &= behind - nearest >= MIN_CLEARANCE_MM
    return np.where(ok, first, -1)


def clean_hit(rig: Rig, hall: Hall, s_mm: float, pan: float, tilt: float) -> int | None:
    """The surface a reading at one pose would measure, if it is unambiguous (else None)."""
    j = int(clean_hits(rig, hall, [s_mm], [pan], [tilt])[0])
    return None if j < 0 else j


def predict(
    rig: Rig,
    hall: Hall,
    poses: Poses,
    mount: FloatArray | None = None,
    placement: FloatArray | None = None,
    ds_mm: float = 0.0,
    offsets_mm: FloatArray | None = None,
) -> FloatArray:
    """Predicted distances with the blocks perturbed: mount and placement δ (6 each), a shift
    of every arc length and each surface moved along its normal."""
    if mount is not None:
        rig = dataclasses.replace(rig, T_r_l=local(rig.T_r_l, mount))
    if placement is not None:
        rig = dataclasses.replace(
            rig, track=rig.track.with_origin(local(rig.track.T_w_track, placement))
        )
    T = rig.T_w_r(poses.s_mm + ds_mm, poses.pan_rad, poses.tilt_rad) @ rig.T_r_l
    o, z = T[..., :3, 3], T[..., :3, 2]
    n = hall.normals[poses.surface]
    p = hall.points[poses.surface]
    if offsets_mm is not None:
        p = p + n * offsets_mm[poses.surface][:, None]
    out: FloatArray = np.einsum("ij,ij->i", n, p - o) / np.einsum("ij,ij->i", n, z)
    return out


def jacobian(f: Callable[[FloatArray], FloatArray], x: FloatArray, steps: FloatArray) -> FloatArray:
    """∂f/∂x by central differences (columns per parameter)."""
    cols = []
    for i, h in enumerate(steps):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((f(x + e) - f(x - e)) / (2.0 * h))
    return np.stack(cols, axis=-1)


def block_variance(spec: RigSpec, rig: Rig, hall: Hall, poses: Poses) -> FloatArray:
    """Variance of each predicted distance from the mount's and the placement's covariance."""
    cov_m = spec.rangefinder.mount.cov()
    cov_p = spec.track.placement.cov()
    zero = np.zeros(6)
    J_m = jacobian(lambda d: predict(rig, hall, poses, mount=d), zero, DIFF_STEPS)
    J_p = jacobian(lambda d: predict(rig, hall, poses, placement=d), zero, DIFF_STEPS)
    var: FloatArray = np.einsum("ij,jk,ik->i", J_m, cov_m, J_m) + np.einsum(
        "ij,jk,ik->i", J_p, cov_p, J_p
    )
    return var


def kinematics_of(spec: RigSpec) -> tuple[Rig, Hall | None]:
    """The calibrated rig's kinematics and its hall."""
    return build_kinematics(spec), Hall.of(spec)
