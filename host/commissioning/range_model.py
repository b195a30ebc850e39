"""A rangefinder reading as a function of the rig's calibrated blocks, for fits and their σ.

The host predicts a reading with `host.geometry.rangefinder` (the beam cast into the surveyed
scene). A fit, or the σ of a quantity solved from a reading, needs that prediction as a smooth
function of the blocks that carry uncertainty: the mount T_r_l and the track's placement
T_w_track (each moved by a local perturbation T · exp(δ), the rig schema's convention), the
trolley's arc length, each surveyed surface's offset along its normal, and two scalars of the
track no board view on the first straight sees: where its first corner lies along the track
relative to the zero, and a change of every arc's radius (bent on one jig). Readings keep the
surface the calibrated rig's beam met, so the function has no jumps. `RangeSolver` fits any of
these blocks to readings by Gauss-Newton, each free or held by the rig file's σ as a prior.
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
    corner_mm: float = 0.0,
    radius_mm: float = 0.0,
) -> FloatArray:
    """Predicted distances with the blocks perturbed: mount and placement δ (6 each), a shift
    of every arc length, each surface moved along its normal, the first corner moved along the
    track (`corner_shift`) and every arc's radius changed by `radius_mm`."""
    if mount is not None:
        rig = dataclasses.replace(rig, T_r_l=local(rig.T_r_l, mount))
    if placement is not None:
        rig = dataclasses.replace(
            rig, track=rig.track.with_origin(local(rig.track.T_w_track, placement))
        )
    if radius_mm:
        rig = dataclasses.replace(rig, track=rig.track.with_arc_radius_change(radius_mm))
    if corner_mm:
        rig = corner_shift(rig, corner_mm)
    T = rig.T_w_r(poses.s_mm + ds_mm + corner_mm, poses.pan_rad, poses.tilt_rad) @ rig.T_r_l
    o, z = T[..., :3, 3], T[..., :3, 2]
    n = hall.normals[poses.surface]
    p = hall.points[poses.surface]
    if offsets_mm is not None:
        p = p + n * offsets_mm[poses.surface][:, None]
    out: FloatArray = np.einsum("ij,ij->i", n, p - o) / np.einsum("ij,ij->i", n, z)
    return out


def corner_shift(rig: Rig, corner_mm: float) -> Rig:
    """The track placed `corner_mm` back along its first straight (the track frame's x), for a
    zero `corner_mm` further along: every pose on the first straight stays where it was, the
    first corner comes `corner_mm` sooner (the caller adds `corner_mm` to the arc lengths)."""
    back = make_T(np.eye(3), [-corner_mm, 0.0, 0.0])
    return dataclasses.replace(rig, track=rig.track.with_origin(rig.track.T_w_track @ back))


@dataclass(frozen=True)
class FitTerms:
    """Which blocks a `RangeSolver` fits besides the placement and the surfaces (always held by
    the rig file's σ): the mount's axes (free, or held by the rig file's covariance), a free
    shift of every arc length, the first corner's place (free) and an arc-radius change (held
    by `radius_sigma_mm`, the drawing's σ; None: not fitted)."""

    mount_axes: tuple[int, ...] = (0, 1, 3, 4, 5)
    mount_prior: bool = False
    shift: bool = True
    corner: bool = False
    radius_sigma_mm: float | None = None

    def layout(self) -> dict[str, slice]:
        """Where each block sits in the parameter vector (before the surfaces' offsets)."""
        sizes = {"mount": len(self.mount_axes), "shift": int(self.shift),
                 "corner": int(self.corner), "radius": int(self.radius_sigma_mm is not None),
                 "placement": 6}  # fmt: skip
        out, at = {}, 0
        for name, n in sizes.items():
            out[name] = slice(at, at + n)
            at += n
        return out

    @property
    def free(self) -> int:
        """How many parameters no prior holds."""
        return (
            (0 if self.mount_prior else len(self.mount_axes)) + int(self.shift) + int(self.corner)
        )


class RangeSolver:
    """Gauss-Newton over the `FitTerms` blocks, the placement (prior: the rig file's
    covariance) and one offset per surface (prior: its survey σ), whitened by each reading's σ."""

    def __init__(
        self, rig: Rig, hall: Hall, poses: Poses, d: FloatArray, sig: FloatArray, spec: RigSpec,
        terms: FitTerms,
    ) -> None:  # fmt: skip
        self.rig, self.hall, self.poses, self.d, self.sig = rig, hall, poses, d, sig
        self.terms, self.at = terms, terms.layout()
        self.k = len(hall.points)
        self.n = self.at["placement"].stop + self.k

        def whiten(cov: FloatArray) -> FloatArray:  # a zero σ pins that component
            out: FloatArray = np.linalg.inv(np.linalg.cholesky(cov + 1e-12 * np.eye(len(cov))))
            return out

        axes = list(terms.mount_axes)
        self.prior_p = whiten(spec.track.placement.cov())
        self.prior_m = whiten(spec.rangefinder.mount.cov()[np.ix_(axes, axes)])
        self.prior_b = 1.0 / np.maximum(hall.sigma_mm, 1e-6)
        self.prior_r = 1.0 / max(terms.radius_sigma_mm or 0.0, 1e-6)
        self.steps = np.concatenate([DIFF_STEPS[axes], [1e-3] * (int(terms.shift) + int(
            terms.corner) + int(terms.radius_sigma_mm is not None)), DIFF_STEPS,
            np.full(self.k, 1e-3)])  # fmt: skip

    def value(self, x: FloatArray, block: str) -> float:
        """A scalar block's value in x (0 when it is not fitted)."""
        sl = self.at[block]
        return float(x[sl][0]) if sl.stop > sl.start else 0.0

    def ranges(self, x: FloatArray) -> FloatArray:
        m = np.zeros(6)
        m[list(self.terms.mount_axes)] = x[self.at["mount"]]
        return predict(
            self.rig, self.hall, self.poses, m, x[self.at["placement"]], self.value(x, "shift"),
            x[self.at["placement"].stop :], self.value(x, "corner"), self.value(x, "radius"),
        )  # fmt: skip

    def _residuals(self, x: FloatArray, inliers: np.ndarray) -> FloatArray:
        data = ((self.d - self.ranges(x)) / self.sig)[inliers]
        p = self.at["placement"]
        priors = [-self.prior_p @ x[p], -self.prior_b * x[p.stop :]]
        if self.terms.mount_prior:
            priors.append(-self.prior_m @ x[self.at["mount"]])
        if self.terms.radius_sigma_mm is not None:
            priors.append(-self.prior_r * x[self.at["radius"]])
        return np.concatenate([data, *priors])

    def chi2_dof(self, x: FloatArray, inliers: np.ndarray) -> float:
        data = ((self.d - self.ranges(x)) / self.sig)[inliers]
        return float(data @ data) / max(int(inliers.sum()) - self.terms.free, 1)

    def solve(self, inliers: np.ndarray, iterations: int = 20) -> tuple[FloatArray, FloatArray]:
        """The minimum and the whitened Jacobian there (rows: inlier data, then priors)."""
        x = np.zeros(self.n)
        J = np.zeros((0, x.size))
        for _ in range(iterations):
            J = -jacobian(lambda v: self._residuals(v, inliers), x, self.steps)
            step = np.linalg.lstsq(J, self._residuals(x, inliers), rcond=None)[0]
            x = x + step
            if np.all(np.abs(step) < 0.1 * self.steps):
                break
        J = -jacobian(lambda v: self._residuals(v, inliers), x, self.steps)
        return x, J


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
