"""Error budget: the predicted σ of the overlay, in pixels, at any pose, from every input's σ.

The overlay of a workpiece point X_p is u = π_θ(T_c_w(s, pan, tilt) · T_w_p · X_p) with

    T_w_c = T_w_track·exp(δk) · T_track_t(s) · T_t_r · R_head(pan, tilt) · M_cr·exp(δm)

Every calibrated quantity enters: the intrinsics θ (10, Table 1's and p1, p2, k3), M_cr and the
track placement and the workpiece frame (local perturbations δ = (ω, t), as the rig file keeps
their covariances), the arc length s as the controller's zero (`track.home`, shared with all
that was measured through it) plus the error beyond it (the chain filter's σ; 0 for the
encoder), plus the stamp's error × speed (a stamp off by δt, from clock sync or the exposure
latency's σ, puts the trolley v·δt away), and the head angles (their noise). Blocks solved
together are correlated (the rig file's `[covariance]`: a focal length a little long and a
camera a little farther away draw the same overlay), and the cross terms enter Σ. First order:
Σ_u = J Σ Jᵀ with J by central differences over all 33 inputs; each source's share is its own
block's J Σ Jᵀ (the shares do not add up to the total when sources are correlated: the cross
terms are in the total only). `monte_carlo` samples the same inputs through the same
projection; the test holds the two together.

What it predicts: the spread of the overlay's error over rigs calibrated like this one, i.e.
drawn minus true pixel of a workpiece point, whose frame is known as the rig file says. A
workpiece surveyed through the rig itself shares the rig's errors, which then cancel in part:
the budget sees that only when the survey writes its cross terms into `[covariance]`
(`host.rig.joint_covariance`); without them it predicts an independently surveyed workpiece.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from host.geometry.camera import CameraModel
from host.geometry.head import Rig, head_rotation
from host.geometry.track import Segment as TrackSegment
from host.geometry.track import Track
from host.geometry.transforms import FloatArray, invert_T, make_T, rotvec_to_R, transform_points
from host.rig import (
    COVARIANCE_BLOCKS,
    INTRINSIC_KEYS,
    RigSpec,
    build_camera,
    build_kinematics,
    covariance_over,
    workpiece_pose,
)

CAMERA_KEYS = INTRINSIC_KEYS
SOURCES = ("intrinsics", "m_cr", "track", "workpiece", "arc_length", "head", "arc_radius", "home")
# The rig file's block of each calibrated source (their cross terms come from `[covariance]`).
RIG_BLOCKS = {
    "intrinsics": "camera.intrinsics",
    "m_cr": "head.m_cr",
    "track": "track.placement",
    "workpiece": "workpiece.frame",
    "home": "track.home",
}
SLICES = {
    "intrinsics": slice(0, 10),
    "m_cr": slice(10, 16),
    "track": slice(16, 22),
    "workpiece": slice(22, 28),
    "arc_length": slice(28, 29),
    "head": slice(29, 31),
    "arc_radius": slice(31, 32),
    "home": slice(32, 33),
}
N_INPUTS = 33
STEPS = np.concatenate([
    [1e-3] * 5, [1e-6] * 5,  # intrinsics: px, then distortion
    [1e-7] * 3 + [1e-4] * 3, [1e-7] * 3 + [1e-4] * 3, [1e-7] * 3 + [1e-4] * 3,  # poses
    [1e-4], [1e-7, 1e-7], [1e-3], [1e-4],  # s mm, head rad, arc radius mm, home mm
])  # fmt: skip


def _zeros6() -> FloatArray:
    return np.zeros((6, 6))


@dataclass(frozen=True)
class BudgetInputs:
    """The rig as calibrated and the covariance of everything in it."""

    rig: Rig
    camera: CameraModel
    T_w_p: FloatArray
    camera_cov: FloatArray = field(default_factory=lambda: np.zeros((10, 10)))
    m_cr_cov: FloatArray = field(default_factory=_zeros6)
    track_cov: FloatArray = field(default_factory=_zeros6)
    workpiece_cov: FloatArray = field(default_factory=_zeros6)
    sigma_s_mm: float = 0.0  # the arc length's error beyond the zero's (the chain filter's σ)
    sigma_head_rad: tuple[float, float] = (0.0, 0.0)  # pan, tilt noise
    sigma_clock_s: float = 0.0  # clock-sync error of a frame's stamp
    speed_mm_s: float = 0.0  # the trolley's speed (the stamp error's lever)
    # 2-D RMS noise of a *detected* image point (the intrinsics fit's residual): not part of
    # the overlay's σ (the overlay is drawn, not detected), added when predicting a measurement
    pixel_noise_px: float = 0.0
    sigma_latency_s: float = 0.0  # the exposure latency's σ (another error of the stamp)
    sigma_arc_radius_mm: float = 0.0  # of every arc's radius, one error shared by the arcs
    sigma_home_mm: float = 0.0  # the controller's zero: in every arc length, shared by surveys
    # N_INPUTS² cross terms between sources (their own diagonal blocks are ignored: those are the
    # fields above, which a caller may replace alone), None: independent sources
    cross: FloatArray | None = None

    def covariance(self) -> FloatArray:
        """The N_INPUTS² input covariance: each source's block and the cross terms between them."""
        S = np.zeros((N_INPUTS, N_INPUTS))
        if self.cross is not None:
            S[:] = self.cross
            for sl in SLICES.values():
                S[sl, sl] = 0.0
        S[SLICES["intrinsics"], SLICES["intrinsics"]] = self.camera_cov
        S[SLICES["m_cr"], SLICES["m_cr"]] = self.m_cr_cov
        S[SLICES["track"], SLICES["track"]] = self.track_cov
        S[SLICES["workpiece"], SLICES["workpiece"]] = self.workpiece_cov
        stamp_var = self.sigma_clock_s**2 + self.sigma_latency_s**2
        S[28, 28] = self.sigma_s_mm**2 + stamp_var * self.speed_mm_s**2
        S[29, 29], S[30, 30] = self.sigma_head_rad[0] ** 2, self.sigma_head_rad[1] ** 2
        S[31, 31] = self.sigma_arc_radius_mm**2
        S[32, 32] = self.sigma_home_mm**2
        return S


@dataclass(frozen=True)
class Budget:
    """Predicted overlay error at one pose: total and per source, RMS over the points (px)."""

    sigma_px: float
    by_source_px: dict[str, float]
    point_cov: FloatArray  # (N, 2, 2) per-point pixel covariance

    def as_dict(self) -> dict[str, object]:
        """Plain values (status, reports)."""
        return {
            "sigma_px": round(self.sigma_px, 4),
            "by_source_px": {k: round(v, 4) for k, v in self.by_source_px.items()},
        }


def project(
    inputs: BudgetInputs, s_mm: float, pan: float, tilt: float, points_p: FloatArray, d: FloatArray
) -> FloatArray:
    """Pixels (N,2) of workpiece points with every input perturbed by d (N_INPUTS,)."""
    vals = {k: getattr(inputs.camera, k) + d[i] for i, k in enumerate(CAMERA_KEYS)}
    cam = dataclasses.replace(inputs.camera, **vals)
    uv, _ = cam.project_world(_T_c_p(inputs, s_mm, pan, tilt, d), points_p)
    return uv


def _T_c_p(inputs: BudgetInputs, s_mm: float, pan: float, tilt: float, d: FloatArray) -> FloatArray:
    """The workpiece in the camera with the pose inputs (10:) perturbed by d."""
    rig, s = inputs.rig, s_mm + d[28] + d[32]
    track = rig.track
    if d[31] != 0.0:  # the arcs bent to another radius; s on the drawn loop
        s = float(track.wrap(s)) if track.closed else s
        track = _bent(track, float(d[31]))
    T_w_k = rig.track.T_w_track @ _exp(d[16:22])
    T_w_c = (T_w_k @ track.local_pose(s) @ rig.T_t_r
             @ head_rotation(pan + d[29], tilt + d[30]) @ rig.T_r_c @ _exp(d[10:16]))  # fmt: skip
    out: FloatArray = invert_T(T_w_c) @ inputs.T_w_p @ _exp(d[22:28])
    return out


def jacobian(
    inputs: BudgetInputs, s_mm: float, pan: float, tilt: float, points_p: FloatArray
) -> FloatArray:
    """∂u/∂inputs (2N × N_INPUTS) by central differences: the intrinsics' on the points in the
    camera, the pose inputs' in one projection, each changing one factor of the chain (a
    status computes this at every new pose)."""
    pts = np.asarray(points_p, dtype=np.float64).reshape(-1, 3)
    J = np.empty((2 * len(pts), N_INPUTS))
    first = len(CAMERA_KEYS)
    Ts = _pose_perturbed(inputs, s_mm, pan, tilt)
    X_c = transform_points(Ts[0], pts)
    cam = inputs.camera
    for j, key in enumerate(CAMERA_KEYS):
        h = float(STEPS[j])
        up, _ = dataclasses.replace(cam, **{key: getattr(cam, key) + h}).project(X_c)
        dn, _ = dataclasses.replace(cam, **{key: getattr(cam, key) - h}).project(X_c)
        J[:, j] = (up - dn).ravel() / (2 * h)
    T = Ts[1:]
    uv, _ = cam.project(np.einsum("mij,nj->mni", T[:, :3, :3], pts) + T[:, None, :3, 3])
    diff = (uv[0::2] - uv[1::2]) / (2 * STEPS[first:, None, None])
    J[:, first:] = diff.reshape(N_INPUTS - first, -1).T
    return J


def _pose_perturbed(inputs: BudgetInputs, s_mm: float, pan: float, tilt: float) -> FloatArray:
    """T_c_p unperturbed, then with each pose input (10:) at +step and −step, (1 + 2·23, 4, 4)."""
    rig = inputs.rig

    def camera_in_track(s: float, p: float, t: float, track: Track = rig.track) -> FloatArray:
        out: FloatArray = track.local_pose(s) @ rig.T_t_r @ head_rotation(p, t) @ rig.T_r_c
        return out

    Q = invert_T(rig.track.T_w_track) @ inputs.T_w_p  # the workpiece in the track's frame
    C_inv = invert_T(camera_in_track(s_mm, pan, tilt))
    T0 = C_inv @ Q
    out = [T0]
    for j in range(len(CAMERA_KEYS), N_INPUTS):
        for h in (STEPS[j], -STEPS[j]):
            if j < 16:  # M_cr: T_w_c·exp(δ)
                T = invert_T(_step_exp(j - 10, h)) @ T0
            elif j < 22:  # the track placement: T_w_track·exp(δ)
                T = C_inv @ invert_T(_step_exp(j - 16, h)) @ Q
            elif j < 28:  # the workpiece frame: T_w_p·exp(δ)
                T = T0 @ _step_exp(j - 22, h)
            elif j in (28, 32):  # the arc length, or the zero it counts from
                T = invert_T(camera_in_track(s_mm + h, pan, tilt)) @ Q
            elif j < 31:
                da = (h, 0.0) if j == 29 else (0.0, h)
                T = invert_T(camera_in_track(s_mm, pan + da[0], tilt + da[1])) @ Q
            else:  # the arcs bent (T_w_track kept: Q holds)
                track = rig.track
                s = float(track.wrap(s_mm)) if track.closed else s_mm
                T = invert_T(camera_in_track(s, pan, tilt, _bent(track, float(h)))) @ Q
            out.append(T)
    return np.array(out)


@functools.lru_cache(maxsize=32)
def _step_exp(axis: int, h: float) -> FloatArray:
    """exp of a step h along one local axis (ω 0-2, t 3-5)."""
    d = np.zeros(6)
    d[axis] = h
    return _exp(d)


def overlay_sigma(
    inputs: BudgetInputs, s_mm: float, pan: float, tilt: float, points_p: FloatArray
) -> Budget:
    """First-order predicted overlay σ at a pose (RMS over the points of the 2-D error)."""
    pts = visible(inputs, s_mm, pan, tilt, points_p)
    if len(pts) == 0:  # nothing of the model in view: no overlay to predict
        return Budget(float("nan"), dict.fromkeys(SOURCES, float("nan")), np.zeros((0, 2, 2)))
    J = jacobian(inputs, s_mm, pan, tilt, pts)
    S = inputs.covariance()
    total = _rms(J, S, len(pts))
    by = {name: _rms(J[:, sl], S[sl, sl], len(pts)) for name, sl in SLICES.items()}
    Jp = J.reshape(len(pts), 2, N_INPUTS)
    blocks = np.einsum("nai,ij,nbj->nab", Jp, S, Jp)
    return Budget(total, by, blocks)


def visible(
    inputs: BudgetInputs, s_mm: float, pan: float, tilt: float, points_p: FloatArray
) -> FloatArray:
    """The points that land in the image (beyond it the lens model is not calibrated)."""
    pts = np.asarray(points_p, dtype=np.float64).reshape(-1, 3)
    uv = project(inputs, s_mm, pan, tilt, pts, np.zeros(N_INPUTS))
    w, h = inputs.camera.width, inputs.camera.height
    ok = (
        np.isfinite(uv).all(axis=1)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] < w)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] < h)
    )
    out: FloatArray = pts[ok]
    return out


def monte_carlo(
    inputs: BudgetInputs,
    s_mm: float,
    pan: float,
    tilt: float,
    points_p: FloatArray,
    n: int,
    seed: int,
) -> float:
    """σ of the overlay by sampling every input (RMS over points and samples)."""
    pts = visible(inputs, s_mm, pan, tilt, points_p)
    rng = np.random.default_rng(seed)
    S = inputs.covariance()
    L = _factor(S)
    base = project(inputs, s_mm, pan, tilt, pts, np.zeros(N_INPUTS))
    sq = 0.0
    for _ in range(n):
        d = L @ rng.standard_normal(N_INPUTS)
        e = project(inputs, s_mm, pan, tilt, pts, d) - base
        sq += float(np.mean(np.sum(e * e, axis=1)))
    return float(np.sqrt(sq / n))


def points_sigma(
    inputs: BudgetInputs, poses: Sequence[tuple[float, float, float]], points_p: FloatArray
) -> list[float]:
    """Predicted σ at several (s, pan, tilt) poses."""
    return [overlay_sigma(inputs, s, p, t, points_p).sigma_px for s, p, t in poses]


def inputs_from_rig(
    spec: RigSpec, sigma_s_mm: float = 0.0, speed_mm_s: float = 0.0
) -> BudgetInputs:
    """The budget of a rig file at a trolley speed: each block's covariance and the cross terms
    of `[covariance]` (the zero's too: surveys and the head run saw the track through it); the
    arc length's error beyond the zero's (`sigma_s_mm`: the chain filter's; 0 for the encoder,
    which counts from the zero exactly); the head's angle noise; the stamp's clock-sync and
    latency σ."""
    names = tuple(RIG_BLOCKS.values())
    joint = covariance_over(spec, names)
    at = np.cumsum([0, *(COVARIANCE_BLOCKS[n] for n in names)])
    where = {src: slice(at[i], at[i + 1]) for i, src in enumerate(RIG_BLOCKS)}
    blocks = {src: joint[sl, sl] for src, sl in where.items()}
    cross = np.zeros((N_INPUTS, N_INPUTS))
    for a, sa in where.items():
        for b, sb in where.items():
            cross[SLICES[a], SLICES[b]] = joint[sa, sb]
    intr = spec.camera.intrinsics
    noise = intr.provenance.residual if intr.provenance.residual_unit == "px" else None
    head = spec.head.angle_noise.sigma
    return BudgetInputs(
        build_kinematics(spec), build_camera(spec), workpiece_pose(spec),
        blocks["intrinsics"], blocks["m_cr"], blocks["track"], blocks["workpiece"], sigma_s_mm,
        (head, head), spec.camera.clock_sync.sigma / 1e3, speed_mm_s,
        pixel_noise_px=float(noise or 0.0), sigma_latency_s=spec.camera.latency.sigma / 1e3,
        cross=cross if spec.covariance is not None else None,
        sigma_arc_radius_mm=spec.track.arc_radius_sigma_mm,
        sigma_home_mm=float(np.sqrt(blocks["home"][0, 0])),
    )  # fmt: skip


def _rms(J: FloatArray, S: FloatArray, n: int) -> float:
    """sqrt(trace(J S Jᵀ) / n): the RMS over points of the 2-D error's σ."""
    return float(np.sqrt(max(np.einsum("ij,jk,ik->", J, S, J), 0.0) / n))


def _factor(S: FloatArray) -> FloatArray:
    """A square root of a PSD matrix (eigen, so zero variances are fine)."""
    w, V = np.linalg.eigh(S)
    out: FloatArray = V * np.sqrt(np.clip(w, 0.0, None))
    return out


def _bent(track: Track, d_radius_mm: float) -> Track:
    """The track with every arc's radius d_radius_mm larger (its angle kept), left open."""
    segs = []
    for g in track.segments:
        if g.curvature_per_mm == 0.0:
            segs.append(g)
            continue
        r = 1.0 / abs(g.curvature_per_mm) + d_radius_mm
        angle = g.length_mm * g.curvature_per_mm
        segs.append(TrackSegment(r * abs(angle), math.copysign(1.0 / r, angle)))
    return Track(tuple(segs), track.T_w_track, closed=False)


def _exp(d: FloatArray) -> FloatArray:
    """Local perturbation (ω, t) as a transform (the rig file's convention)."""
    return make_T(rotvec_to_R(d[:3]), d[3:6])
