"""`orbitar survey track`: where the first corner lies relative to the zero, and the arcs' radius.

Every other commissioning observation (board views, the home survey, the workpiece) is taken on
the first straight, where a shift of the zero (`track.home`) and an opposite shift of the track's
placement along that straight give the same poses: only their sum is known, and the first corner
sits by their difference off. Nor does anything measure the arcs' radius (a closed loop's arcs
are bent on one jig: one error shared by all). Both move every pose past the first corner.

With the trolley at rest at stations on the first straight (for contrast) and through the first
arc (or any given), the head turns the rangefinder at the surveyed hall. The readings are fitted
by `range_model.RangeSolver` with the corner's place (free), a shared change of the arcs' radius
(prior: the rig file's `arc_radius_sigma_mm`), the mount and the placement (priors: their
covariance in the rig file) and each surface's offset along its normal (prior: its survey σ);
the two track scalars' σ are their marginals (scaled up when χ²/dof > 1). An open track's arcs
are bent one by one: there the radius is not fitted, only the corner's place.

What is written keeps the first straight's poses: the zero moves by δ along the track and the
placement by −δ along the first straight (the track frame's x), and a joint covariance that
covers them is carried through the same linear map; marks a survey measured in the old track
coordinates move by δ with them (marks from the drawing are already in the track's own). The
radius goes into every arc segment, its σ into `arc_radius_sigma_mm`, its provenance into
`track.arcs`.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.commissioning.frames import RangeTap
from host.commissioning.jobs import Progress
from host.commissioning.motion import AbortedError, RigIO
from host.commissioning.plan import ViewTarget
from host.commissioning.range_model import FitTerms, RangeSolver, kinematics_of
from host.commissioning.rangefinder_run import (
    RANK_RTOL,
    RangeSample,
    capture,
    clean_readings,
    default_plan,
    robust_solve,
)
from host.commissioning.report import Page, pyplot, text_table
from host.geometry.transforms import FloatArray, make_T
from host.rig import (
    COVARIANCE_BLOCKS,
    JointCovariance,
    Marks,
    Pose6,
    Provenance,
    RigSpec,
    travel_limits_mm,
)
from host.rig.covariance import covariance_over, joint_covariance
from host.rig.schema import NOMINAL

DEFAULT_PANS = 6  # 17 poses on the demo's runway: σ ≈ 0.13 mm for both
CONTRAST_BEFORE_MM = 1000.0  # the first straight's station, this far before the corner
ARC_FRACTIONS = (0.3, 0.7)  # stations through the arc, as fractions of its length
HORIZON_TILT_RAD = math.pi / 2  # the head's tilt that puts the beam level (look ahead)


@dataclass(frozen=True)
class TrackThresholds:
    """The stated pass/fail thresholds of a track survey."""

    max_corner_sigma_mm: float = 1.5
    max_radius_sigma_mm: float = 1.5
    max_rms_mm: float = 2.0
    min_poses: int = 12
    max_rejected: float = 0.25

    def describe(self) -> str:
        """The thresholds in one line."""
        return (
            f"corner σ ≤ {self.max_corner_sigma_mm} mm, radius σ ≤ {self.max_radius_sigma_mm} mm,"
            f" RMS ≤ {self.max_rms_mm} mm, ≥ {self.min_poses} poses, "
            f"≤ {self.max_rejected:.0%} rejected"
        )


@dataclass(frozen=True)
class FirstCorner:
    """The track's first straight and the arc after it (drawing values)."""

    straight_mm: float  # arc length where the first arc begins
    arc_mm: float  # the arc's length
    radius_mm: float
    closed: bool


@dataclass
class TrackFit:
    """A track survey's outcome (the corner and radius only when they could be solved)."""

    passed: bool
    reasons: list[str]
    corner_mm: float = math.nan  # δ: the zero moves by δ, the placement by −δ along x
    corner_sigma_mm: float = math.nan
    radius_change_mm: float = math.nan  # 0 and σ nan when not fitted (an open track)
    radius_sigma_mm: float = math.nan
    radius_fitted: bool = False
    correlation: float = math.nan
    residuals_mm: FloatArray = field(default_factory=lambda: np.zeros(0))
    s_mm: FloatArray = field(default_factory=lambda: np.zeros(0))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    surfaces: list[str] = field(default_factory=list)
    rms_mm: float = math.nan
    chi2_dof: float = math.nan
    poses: int = 0

    def summary(self) -> dict[str, Any]:
        """Plain numbers for the op's result."""
        out: dict[str, Any] = {"passed": self.passed, "reasons": self.reasons, "poses": self.poses}
        if math.isfinite(self.corner_mm):
            rows: list[list[str | float]] = [
                ["corner along the track δ (mm)", round(self.corner_mm, 3),
                 round(self.corner_sigma_mm, 3)],
                ["arc radius change (mm)", round(self.radius_change_mm, 3),
                 round(self.radius_sigma_mm, 3) if self.radius_fitted else "not fitted"],
            ]  # fmt: skip
            out.update(
                corner_mm=self.corner_mm,
                corner_sigma_mm=self.corner_sigma_mm,
                radius_change_mm=self.radius_change_mm,
                radius_sigma_mm=self.radius_sigma_mm if self.radius_fitted else None,
                correlation=round(self.correlation, 3),
                rms_mm=round(self.rms_mm, 3),
                chi2_dof=round(self.chi2_dof, 3),
                rejected=int((~self.inliers).sum()),
                surfaces=self.surfaces,
                table=text_table(["track change", "value", "σ"], rows),
            )
        return out


def first_corner(spec: RigSpec) -> FirstCorner | str:
    """The first straight and the arc after it, or why the track has none."""
    segs = spec.track.segments
    if len(segs) < 2 or segs[0].kind != "straight" or segs[1].kind != "arc":
        return "the track does not start with a straight followed by an arc: no first corner"
    closed = kinematics_of(spec)[0].track.closed
    return FirstCorner(segs[0].length_mm, segs[1].arc_length_mm, segs[1].radius_mm, closed)


def default_stations(spec: RigSpec, corner: FirstCorner) -> list[float]:
    """Arc lengths to range from: one on the first straight and two through the arc, within the
    travel (a station past the arc adds little: on the demo's runway σ 0.12 → 0.13 mm without
    it, and the travel there and back)."""
    lo, hi = travel_limits_mm(spec.track)
    c = corner.straight_mm
    wanted = [c - CONTRAST_BEFORE_MM, *(c + f * corner.arc_mm for f in ARC_FRACTIONS)]
    return [float(s) for s in wanted if lo + 100.0 <= s <= hi - 100.0]


def plan(
    spec: RigSpec, stations_mm: list[float] | None, pans: int, tilt_limits: tuple[float, float]
) -> list[ViewTarget] | str:
    """The poses (level beams at the walls, pans around) or why there are none."""
    corner = first_corner(spec)
    if isinstance(corner, str):
        return corner
    where = stations_mm if stations_mm is not None else default_stations(spec, corner)
    tilt = min(HORIZON_TILT_RAD, tilt_limits[1])
    views = default_plan(spec, where, pans, [tilt], tilt_limits)
    return views or "no pose of the plan puts the beam cleanly on a surveyed surface"


def fit_track(
    spec: RigSpec, samples: list[RangeSample], limits: TrackThresholds | None = None
) -> TrackFit:
    """Solve the corner's place and the arcs' radius change from the samples and judge them
    (nothing here writes)."""
    limits = limits or TrackThresholds()
    corner = first_corner(spec)
    if isinstance(corner, str):
        return TrackFit(False, [corner])
    rig, hall = kinematics_of(spec)
    if hall is None:
        return TrackFit(False, ["the rig file lists no surveyed surfaces to range against"])
    got = clean_readings(spec, rig, hall, samples)
    if got.distinct < limits.min_poses:
        return TrackFit(False, [
            f"readings from {got.distinct} distinct poses: the track survey needs "
            f"≥ {limits.min_poses} with clean hits, on the first straight, through the first "
            "arc and past it"], poses=got.distinct)  # fmt: skip
    past = got.poses.s_mm > corner.straight_mm + 1.0
    if past.sum() < 2 or (~past).sum() < 1:
        return TrackFit(False, [
            "the readings do not reach past the first corner (or none is on the straight "
            "before it): take stations through and after the arc"], poses=got.distinct)  # fmt: skip
    fit_radius = corner.closed
    terms = FitTerms(
        (0, 1, 2, 3, 4, 5), mount_prior=True, shift=False, corner=True,
        radius_sigma_mm=max(spec.track.arc_radius_sigma_mm, 1e-3) if fit_radius else None,
    )  # fmt: skip
    solver = RangeSolver(rig, got.hall, got.poses, got.d, got.sig, spec, terms)
    x, J, inliers, r = robust_solve(solver, limits.min_poses)
    names = [hall.scene.surfaces[j].name for j in got.used]
    base = TrackFit(False, [], residuals_mm=r, s_mm=got.poses.s_mm, inliers=inliers,
                    surfaces=names, poses=got.distinct)  # fmt: skip
    at = solver.at
    cols = [at["corner"].start] + ([at["radius"].start] if fit_radius else [])
    sv = np.linalg.svd(J[:, cols], compute_uv=False)
    if sv[-1] <= RANK_RTOL * max(float(np.linalg.svd(J, compute_uv=False)[0]), 1e-300):
        base.reasons = ["the readings do not fix the corner (singular): range from the arc"]
        return base
    chi2 = solver.chi2_dof(x, inliers)
    cov = np.linalg.inv(J.T @ J) * max(1.0, chi2)
    sub = cov[np.ix_(cols, cols)]
    sigma = np.sqrt(np.diag(sub))
    base.corner_mm, base.corner_sigma_mm = float(x[cols[0]]), float(sigma[0])
    base.radius_fitted = fit_radius
    if fit_radius:
        base.radius_change_mm, base.radius_sigma_mm = float(x[cols[1]]), float(sigma[1])
        base.correlation = float(sub[0, 1] / (sigma[0] * sigma[1]))
    else:
        base.radius_change_mm = 0.0
    base.rms_mm = float(np.sqrt(np.mean(r[inliers] ** 2)))
    base.chi2_dof = chi2
    reasons = []
    if base.rms_mm > limits.max_rms_mm:
        reasons.append(f"RMS residual {base.rms_mm:.2f} mm > {limits.max_rms_mm} mm")
    if base.corner_sigma_mm > limits.max_corner_sigma_mm:
        reasons.append(f"corner σ {base.corner_sigma_mm:.2f} mm > {limits.max_corner_sigma_mm} mm")
    if fit_radius and base.radius_sigma_mm > limits.max_radius_sigma_mm:
        reasons.append(f"radius σ {base.radius_sigma_mm:.2f} mm > {limits.max_radius_sigma_mm} mm")
    rejected = float((~inliers).mean())
    if rejected > limits.max_rejected:
        reasons.append(f"{rejected:.0%} of the poses rejected as outliers")
    base.passed = not reasons
    if base.passed:
        radius = (
            f", arc radius {base.radius_change_mm:+.2f} ± {base.radius_sigma_mm:.2f} mm"
            if fit_radius else " (an open track: radius not fitted)"
        )  # fmt: skip
        reasons.append(
            f"first corner {base.corner_mm:+.2f} ± {base.corner_sigma_mm:.2f} mm along the "
            f"track{radius}, from {int(inliers.sum())} poses on {len(names)} surfaces: RMS "
            f"{base.rms_mm:.2f} mm"
        )
    base.reasons = reasons
    return base


def track_update(spec: RigSpec, fit: TrackFit, samples: int) -> dict[str, Any]:
    """The rig file's blocks a passing survey replaces: the zero (+δ), the placement (−δ along
    its x), the joint covariance carried through that map, surveyed marks (+δ), and on a closed
    loop every arc's radius with its σ and provenance."""
    if not fit.passed or not math.isfinite(fit.corner_mm):
        raise ValueError("only a passing survey is written")
    track = spec.track
    delta, var = fit.corner_mm, fit.corner_sigma_mm**2
    prov = Provenance.now(
        "survey track (rangefinder on the surveyed hall through the first corner)",
        fit.rms_mm, "mm", int(fit.inliers.sum()), f"{samples} readings per pose",
    )  # fmt: skip
    # errors after (zero e_h, placement's local e_p): e_h' = n, e_p' = e_p + e_h·x̂ − n·x̂ with
    # n the survey's error (σ from the fit); every other block unchanged
    names = spec.covariance.names if spec.covariance is not None else ()
    blocks = [n for n in names if n not in ("track.home", "track.placement")]
    blocks += ["track.home", "track.placement"]
    C = covariance_over(spec, blocks)
    at = np.cumsum([0, *(COVARIANCE_BLOCKS[n] for n in blocks)])
    h, p = int(at[-3]), int(at[-2])  # the zero's index, the placement's first
    G = np.eye(len(C))
    G[h, h] = 0.0
    G[p + 3, h] = 1.0  # tx (local, along the first straight)
    g = np.zeros(len(C))
    g[h], g[p + 3] = 1.0, -1.0
    C2 = G @ C @ G.T + var * np.outer(g, g)
    C2 = 0.5 * (C2 + C2.T)
    home = dataclasses.replace(track.home, value=track.home.value + delta,
                               sigma=math.sqrt(C2[h, h]), provenance=prov)  # fmt: skip
    cov_p = C2[p : p + 6, p : p + 6]
    sig_p = np.sqrt(np.diag(cov_p))
    placement = Pose6(
        track.placement.matrix @ make_T(np.eye(3), [-delta, 0.0, 0.0]),
        (float(sig_p[0]), float(sig_p[1]), float(sig_p[2])),
        (float(sig_p[3]), float(sig_p[4]), float(sig_p[5])),
        cov_p, dataclasses.replace(track.placement.provenance, note=(
            f"{track.placement.provenance.note}; moved {-delta:+.2f} mm along x by survey "
            "track").lstrip("; ")),
    )  # fmt: skip
    # the joint block over what it named and the two moved blocks: their cross term (−σ² of
    # the survey, and what each shares with the camera's blocks) is what keeps the sum's σ
    at_of = {n: slice(int(at[i]), int(at[i + 1])) for i, n in enumerate(blocks)}
    mats = {n: C2[at_of[n], at_of[n]] for n in blocks}
    pairs = {(a, b): C2[at_of[a], at_of[b]] for a in blocks for b in blocks if a < b}
    joint_prov = spec.covariance.provenance if spec.covariance is not None else prov
    joint: JointCovariance = joint_covariance(mats, pairs, joint_prov)
    out: dict[str, Any] = {"track.home": home, "track.placement": placement, "covariance": joint}
    if track.marks.s_mm and track.marks.provenance.method != NOMINAL:
        out["track.marks"] = Marks(tuple(s + delta for s in track.marks.s_mm),
                                   track.marks.sigma_mm, track.marks.provenance)  # fmt: skip
    if fit.radius_fitted:
        dr = fit.radius_change_mm
        out["track.segments"] = tuple(
            dataclasses.replace(s, radius_mm=s.radius_mm + dr) if s.kind == "arc" else s
            for s in track.segments
        )
        out["track.arc_radius_sigma_mm"] = fit.radius_sigma_mm
        out["track.arcs"] = prov
    return out


async def survey_track(
    io: RigIO, tap: RangeTap, spec: RigSpec, views: list[ViewTarget], samples: int,
    limits: TrackThresholds, progress: Progress,
) -> tuple[TrackFit, int]:  # fmt: skip
    """Range from each planned pose at rest, then fit; the fit and the poses with no reading."""
    snap = io.snapshot()
    if snap.get("position_mm") is None or snap.get("state") != "READY":
        raise AbortedError(f"the trolley must be homed and at rest (state {snap.get('state')})")
    got, missed = await capture(io, tap, views, samples, progress)
    progress["phase"] = "solving"
    return await asyncio.to_thread(fit_track, spec, got, limits), missed


def track_page(fit: TrackFit, limits: TrackThresholds) -> Page:
    """The report page: the two track scalars with their σ, residuals along the track."""
    plt = pyplot()

    summary = fit.summary()
    pg = Page("Track survey (first corner, arc radius)", fit.passed, fit.reasons,
              limits.describe(), data=summary)  # fmt: skip
    if "table" in summary:
        pg.preformatted.append(("Track change", summary["table"]))
    if len(fit.residuals_mm):
        fig, ax = plt.subplots(figsize=(11, 3.2))
        ok = fit.inliers
        ax.scatter(fit.s_mm[ok], fit.residuals_mm[ok], s=10, label="used")
        ax.scatter(fit.s_mm[~ok], fit.residuals_mm[~ok], s=16, c="r", marker="x",
                   label="rejected")  # fmt: skip
        ax.axhline(0.0, color="k", linewidth=0.6)
        ax.set_xlabel("station arc length (mm)")
        ax.set_ylabel("reading − prediction (mm)")
        ax.legend()
        pg.figures.append(("Residual per pose, along the track", fig))
    return pg
