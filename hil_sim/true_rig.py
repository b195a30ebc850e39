"""The simulator's true rig: the nominal rig description plus seeded installation tolerances.

A built rig is never its drawing: M_cr is off eq. 14 by a few mm and mrad, the lens is off its
datasheet (focal lengths ~1 %, principal point several px, other k1/k2), the track hangs a few mm
off its planned height and its arcs were bent to slightly other radii, the rangefinder sits
askew, and the marks, walls and home switch are where they are, not where a survey with ~1 mm σ
says they are. `true_rig(nominal, seed)` draws one such rig, deterministically per seed. The
host starts from the nominal values only; the truth leaves the simulator only for scoring.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from host.geometry.transforms import FloatArray, R_to_rotvec, make_T, rotvec_to_R
from host.rig import (
    INTRINSIC_KEYS,
    HallSpec,
    Intrinsics,
    Marks,
    Pose6,
    Provenance,
    RigSpec,
    Scalar,
    Segment,
    TrackSpec,
    build_track,
)

TRUTH = Provenance(method="simulator truth")
SALT = 0x5EED_0011  # keeps these draws apart from the plant's own random streams


@dataclass(frozen=True)
class Tolerances:
    """Standard deviations of how far the built rig is from its description (0: exact)."""

    m_cr_mm: float = 3.0
    m_cr_rad: float = 3e-3
    focal_fraction: float = 0.01
    principal_point_px: float = 5.0
    skew: float = 0.2
    k1: float = 0.1
    k2: float = 0.3
    track_height_mm: float = 3.0
    track_xy_mm: float = 3.0
    track_tilt_rad: float = 5e-4  # roll and pitch of the track's plane
    track_yaw_rad: float = 1e-3
    arc_radius_mm: float = 2.0
    rangefinder_mm: float = 2.0
    rangefinder_rad: float = 3e-3
    survey_mm: float = 1.0  # marks, walls and the home position against their survey
    workpiece_mm: float = 3.0
    workpiece_rad: float = 2e-3
    latency_ms: float = 20.0  # frame delivery after exposure (untriggered camera), mean
    latency_jitter_ms: float = 1.0

    @classmethod
    def off(cls) -> Tolerances:
        """A built rig exactly as described (the demo's old behaviour)."""
        zero = {f.name: 0.0 for f in dataclasses.fields(cls)}
        return cls(**zero)

    @property
    def any(self) -> bool:
        """True when any tolerance is non-zero."""
        return any(getattr(self, f.name) for f in dataclasses.fields(self))


def true_rig(nominal: RigSpec, seed: int, tol: Tolerances | None = None) -> RigSpec:
    """One built rig drawn around `nominal`; the same seed gives the same rig."""
    tol = Tolerances() if tol is None else tol
    if not tol.any:
        return nominal
    rng = np.random.default_rng([SALT, seed])
    cam = nominal.camera
    latency = Scalar(cam.latency.value if cam.trigger else tol.latency_ms, 0.0, TRUTH)
    return dataclasses.replace(
        nominal,
        name=f"{nominal.name} (true rig, seed {seed})",
        covariance=None,  # a description's calibration covariance says nothing of the truth
        track=_track(nominal.track, rng, tol),
        hall=_hall(nominal.hall, rng, tol),
        head=dataclasses.replace(
            nominal.head, m_cr=_pose(nominal.head.m_cr, rng, tol.m_cr_rad, tol.m_cr_mm)
        ),
        rangefinder=dataclasses.replace(
            nominal.rangefinder,
            mount=_pose(nominal.rangefinder.mount, rng, tol.rangefinder_rad, tol.rangefinder_mm),
        ),
        camera=dataclasses.replace(
            cam, intrinsics=_intrinsics(cam.intrinsics, rng, tol), latency=latency
        ),
        workpiece=dataclasses.replace(
            nominal.workpiece,
            frame=_pose(nominal.workpiece.frame, rng, tol.workpiece_rad, tol.workpiece_mm),
        ),
    )


def _perturbation(
    rng: np.random.Generator, rad: tuple[float, ...], mm: tuple[float, ...]
) -> FloatArray:
    """exp(δ) for δ drawn with the given σ per axis (the schema's local perturbation)."""
    w = rng.normal(0.0, 1.0, 3) * np.asarray(rad)
    t = rng.normal(0.0, 1.0, 3) * np.asarray(mm)
    return make_T(rotvec_to_R(w), t)


def _pose(p: Pose6, rng: np.random.Generator, sigma_rad: float, sigma_mm: float) -> Pose6:
    """The true transform: the nominal one moved by a drawn local perturbation."""
    delta = _perturbation(rng, (sigma_rad,) * 3, (sigma_mm,) * 3)
    return Pose6(p.matrix @ delta, provenance=TRUTH)


def _intrinsics(i: Intrinsics, rng: np.random.Generator, tol: Tolerances) -> Intrinsics:
    """Focal lengths scaled by ~1 %, principal point moved, other distortion."""
    v = i.as_dict()
    scale = 1.0 + rng.normal(0.0, tol.focal_fraction)
    v["fx"] *= scale * (1.0 + rng.normal(0.0, 0.1 * tol.focal_fraction))
    v["fy"] *= scale * (1.0 + rng.normal(0.0, 0.1 * tol.focal_fraction))
    v["u0"] += rng.normal(0.0, tol.principal_point_px)
    v["v0"] += rng.normal(0.0, tol.principal_point_px)
    v["skew"] += rng.normal(0.0, tol.skew)
    v["k1"] += rng.normal(0.0, tol.k1)
    v["k2"] += rng.normal(0.0, tol.k2)
    values = tuple(v[k] for k in INTRINSIC_KEYS)
    return Intrinsics(values, (0.0,) * len(values), None, TRUTH)


def _track(track: TrackSpec, rng: np.random.Generator, tol: Tolerances) -> TrackSpec:
    """Placement off by mm and mrad, arc radii off, marks off their survey."""
    rad = (tol.track_tilt_rad, tol.track_tilt_rad, tol.track_yaw_rad)
    mm = (tol.track_xy_mm, tol.track_xy_mm, tol.track_height_mm)
    placement = Pose6(track.placement.matrix @ _perturbation(rng, rad, mm), provenance=TRUTH)
    segments = _segments(track, rng, tol.arc_radius_mm)
    marks = tuple(s + rng.normal(0.0, tol.survey_mm) for s in track.marks.s_mm)
    # The home switch stays where the drawing has it: where the controller's zero lands (the
    # first index pulse past the switch) is the plant's to decide, and a survey measures it.
    return dataclasses.replace(
        track, segments=segments, placement=placement, marks=Marks(tuple(sorted(marks)), 0.0, TRUTH)
    )


def _segments(track: TrackSpec, rng: np.random.Generator, sigma_mm: float) -> tuple[Segment, ...]:
    """Arcs bent to other radii: one error per arc on an open track; on a closed loop one error
    shared by all arcs (bent on one jig), which keeps a loop that turns one way closed."""
    closed = build_track(track).closed
    shared = rng.normal(0.0, sigma_mm)
    out = []
    for seg in track.segments:
        if seg.kind != "arc":
            out.append(seg)
            continue
        delta = shared if closed else rng.normal(0.0, sigma_mm)
        out.append(dataclasses.replace(seg, radius_mm=seg.radius_mm + delta))
    candidate = dataclasses.replace(track, segments=tuple(out))
    try:
        if build_track(candidate).closed == closed:
            return tuple(out)
    except ValueError:
        pass
    return track.segments  # a loop whose arcs turn both ways: radii as drawn, placement still off


def _hall(hall: HallSpec, rng: np.random.Generator, tol: Tolerances) -> HallSpec:
    """Each surveyed surface truly sits off its survey along its normal."""
    moved = []
    for s in hall.surfaces:
        n = np.asarray(s.normal) / math.sqrt(sum(x * x for x in s.normal))
        p = np.asarray(s.point_mm) + n * rng.normal(0.0, tol.survey_mm)
        moved.append(dataclasses.replace(s, point_mm=(float(p[0]), float(p[1]), float(p[2]))))
    return HallSpec(tuple(moved), TRUTH)


def parameter_errors(estimate: RigSpec, truth: RigSpec) -> dict[str, dict[str, float]]:
    """Each calibrated parameter: estimate, truth and its σ (for the demo's report)."""
    out: dict[str, dict[str, float]] = {}
    ei, ti = estimate.camera.intrinsics, truth.camera.intrinsics
    for k, sig in zip(INTRINSIC_KEYS, ei.sigma, strict=True):
        out[f"camera.{k}"] = {"estimate": ei.get(k), "truth": ti.get(k), "sigma": sig}
    for name, e, t in (
        ("head.m_cr", estimate.head.m_cr, truth.head.m_cr),
        ("track.placement", estimate.track.placement, truth.track.placement),
        ("rangefinder.mount", estimate.rangefinder.mount, truth.rangefinder.mount),
        ("workpiece.frame", estimate.workpiece.frame, truth.workpiece.frame),
    ):
        delta = np.linalg.inv(e.matrix) @ t.matrix  # truth = estimate · exp(δ)
        axes = ("x", "y", "z")
        for i, ax in enumerate(axes):
            out[f"{name}.t{ax}_mm"] = {
                "estimate": float(e.matrix[i, 3]),
                "truth": float(t.matrix[i, 3]),
                "sigma": e.sigma_mm[i],
                "error_local": float(delta[i, 3]),
            }
        w = _rotvec(delta[:3, :3])
        for i, ax in enumerate(axes):
            out[f"{name}.w{ax}_mrad"] = {
                "estimate": 0.0,
                "truth": 1e3 * float(w[i]),
                "sigma": 1e3 * e.sigma_rad[i],
                "error_local": 1e3 * float(w[i]),
            }
    out["track.home_mm"] = {
        "estimate": estimate.track.home.value,
        "truth": truth.track.home.value,
        "sigma": estimate.track.home.sigma,
    }
    arcs = [
        (e.radius_mm, t.radius_mm)
        for e, t in zip(estimate.track.segments, truth.track.segments, strict=False)
        if e.kind == "arc" and t.kind == "arc"
    ]
    if arcs:  # one error shared by a loop's arcs: the first arc's radius stands for them
        out["track.arc_radius_mm"] = {
            "estimate": arcs[0][0],
            "truth": arcs[0][1],
            "sigma": estimate.track.arc_radius_sigma_mm,
        }
    out["camera.latency_ms"] = {
        "estimate": estimate.camera.latency.value,
        "truth": truth.camera.latency.value,
        "sigma": estimate.camera.latency.sigma,
    }
    return out


def _rotvec(R: FloatArray) -> FloatArray:
    """Rotation vector of a rotation (the log map)."""
    return np.asarray(R_to_rotvec(R), dtype=np.float64)
