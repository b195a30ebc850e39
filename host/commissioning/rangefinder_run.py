"""`orbitar calibrate rangefinder`: the mount T_r_l from readings against the surveyed hall.

The head points the beam at the rig file's surfaces (walls, floor) from many trolley positions
and head angles; each pose gives the mean of `samples` readings. The mount is the local
perturbation T_r_l · exp(δ) that best explains them, by Gauss-Newton over δ = (ωx, ωy, tx, ty,
tz): the roll ωz about the beam moves neither its origin nor its direction, so no reading sees
it; it stays at the rig file's value and σ. The fit also carries what the prediction depends
on and is only known to its survey: the track placement (prior: its covariance in the rig
file), each surface's offset along its normal (prior: its survey σ) and a shift of every arc
length (free: the home may not be surveyed yet, and a pan turns the mount's offset where the
shift stays along the track, so the data separate them). The mount's σ is the marginal of the
whitened Jacobian's inverse (scaled up when χ²/dof > 1); readings off by more than
`OUTLIER_SIGMAS` are rejected and the fit repeated. tz is indistinguishable from a constant
range offset of the instrument, taken to be zero (its datasheet zero).

Walls surveyed to 1 mm beat the commissioning board as a reference (docs/COMMISSIONING.md,
"Why walls and not the board"): each wall's error is one offset shared by all its readings,
which the fit carries, and the beam sweeps metres of lever arm over all of the head's angles,
where the board's pose from the camera adds M_cr's error and its depth σ to every reading and
spans a few degrees of beam direction.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.commissioning.frames import NoFramesError, RangeTap, wait_ranges
from host.commissioning.jobs import Progress
from host.commissioning.motion import RigIO
from host.commissioning.plan import ViewTarget
from host.commissioning.range_model import (
    FitTerms,
    Hall,
    Poses,
    RangeSolver,
    clean_hit,
    kinematics_of,
    local,
)
from host.commissioning.report import Page, pyplot, text_table
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray
from host.rig import Pose6, Provenance, RigSpec, travel_limits_mm

MOUNT_NAMES = ("ωx (mrad)", "ωy (mrad)", "tx (mm)", "ty (mm)", "tz (mm)")
MOUNT_AXES = (0, 1, 3, 4, 5)  # of the schema's (ωx, ωy, ωz, tx, ty, tz): ωz is unobservable
OUTLIER_SIGMAS = 4.0
OUTLIER_ROUNDS = 3

RANK_RTOL = 1e-9
RANGE_TIMEOUT_S = 3.0
MAX_SPREAD_FACTOR = 5.0  # a pose whose readings scatter this much over the noise is on an edge
DEFAULT_STATIONS = 4
DEFAULT_PANS = 8
STATION_MARGIN_MM = 300.0
MIN_TILT_RAD = 0.2


@dataclass(frozen=True)
class MountThresholds:
    """The stated pass/fail thresholds of a mount calibration."""

    max_rms_mm: float = 2.0  # RMS residual of the inliers
    max_sigma_mm: float = 1.5  # σ of each of the beam origin's coordinates (nominal: 3 mm)
    max_sigma_mrad: float = 1.0  # σ of each of the beam direction's tilts
    max_condition: float = 1e3  # of the mount's correlation matrix (near 1: independent)
    min_poses: int = 12
    max_rejected: float = 0.25  # fraction of poses

    def describe(self) -> str:
        """The thresholds in one line."""
        return (
            f"RMS ≤ {self.max_rms_mm} mm, σ ≤ {self.max_sigma_mm} mm and "
            f"≤ {self.max_sigma_mrad} mrad, condition ≤ {self.max_condition:.0f}, "
            f"≥ {self.min_poses} poses, ≤ {self.max_rejected:.0%} rejected"
        )


@dataclass(frozen=True)
class RangeSample:
    """One pose's mean reading: where (arc length, measured head angles) and how many."""

    s_mm: float
    pan_rad: float
    tilt_rad: float
    distance_mm: float
    spread_mm: float = 0.0
    count: int = 1


@dataclass
class MountFit:
    """A mount calibration's outcome (T_r_l and covariance only when it could be solved)."""

    passed: bool
    reasons: list[str]
    before: FloatArray
    T_r_l: FloatArray | None = None
    covariance: FloatArray | None = None  # 6×6, schema order (ωx, ωy, ωz, tx, ty, tz)
    delta: FloatArray | None = None  # the 5 solved components
    sigma: FloatArray | None = None  # their σ (rad, mm)
    residuals_mm: FloatArray = field(default_factory=lambda: np.zeros(0))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    surfaces: list[str] = field(default_factory=list)
    rms_mm: float = math.nan
    chi2_dof: float = math.nan
    condition: float = math.nan
    shift_mm: float = math.nan  # the arc-length shift the fit saw (a home check)
    shift_sigma_mm: float = math.nan
    poses: int = 0

    def summary(self) -> dict[str, Any]:
        """Plain numbers for the op's result."""
        out: dict[str, Any] = {"passed": self.passed, "reasons": self.reasons, "poses": self.poses}
        if self.delta is not None and self.sigma is not None:
            scale = np.array([1e3, 1e3, 1.0, 1.0, 1.0])
            rows: list[list[str | int | float]] = [
                [name, round(float(d * k), 3), round(float(s * k), 3)]
                for name, d, s, k in zip(MOUNT_NAMES, self.delta, self.sigma, scale, strict=True)
            ]
            rows.append(["arc-length shift (mm)", round(self.shift_mm, 2),
                         round(self.shift_sigma_mm, 2)])  # fmt: skip
            out.update(
                rms_mm=round(self.rms_mm, 3),
                chi2_dof=round(self.chi2_dof, 3),
                condition=round(self.condition, 1),
                rejected=int((~self.inliers).sum()),
                mount=None if self.T_r_l is None else self.T_r_l.tolist(),
                table=text_table(["mount change", "value", "σ"], rows),
            )
        return out


def default_plan(
    spec: RigSpec,
    stations_mm: list[float] | None,
    pans: int,
    tilts_rad: list[float] | None,
    tilt_limits: tuple[float, float],
) -> list[ViewTarget]:
    """Poses whose beam meets a surveyed surface cleanly: stations × pans × tilts, in an order
    that sweeps the head rather than swinging it back."""
    rig, hall = kinematics_of(spec)
    if hall is None:
        return []
    if stations_mm is None:
        lo, hi = travel_limits_mm(spec.track)
        lo, hi = max(lo, 0.0) + STATION_MARGIN_MM, min(hi, spec.track.length_mm) - STATION_MARGIN_MM
        stations_mm = list(np.linspace(lo, hi, DEFAULT_STATIONS))
    if tilts_rad is None:
        top = min(tilt_limits[1], math.pi / 2)
        bottom = max(tilt_limits[0], MIN_TILT_RAD)
        tilts_rad = list(np.linspace(bottom, top, 3)) if top > bottom else [top]
    # In ascending order: the pan axis ends at ±180°, so going from +150° to −150° is 300° of
    # travel, not 60° (on the demo's runway that had the survey's head turning for 12 s more).
    ascending = sorted(math.remainder(math.tau * (k + 0.5) / pans, math.tau) for k in range(pans))
    plan = []
    for i, s in enumerate(stations_mm):
        for j, tilt in enumerate(tilts_rad):
            for pan in ascending if (i + j) % 2 == 0 else ascending[::-1]:
                if clean_hit(rig, hall, float(s), pan, float(tilt)) is not None:
                    plan.append(ViewTarget(float(s), pan, float(tilt), f"s={s:.0f}"))
    return plan


async def capture(
    io: RigIO, tap: RangeTap, plan: list[ViewTarget], samples: int, progress: Progress
) -> tuple[list[RangeSample], int]:
    """Drive to each pose, average `samples` readings; the samples and the poses with none."""
    out: list[RangeSample] = []
    missed = 0
    for i, view in enumerate(plan):
        progress.update(phase="ranging", view=i + 1, of=len(plan), accepted=len(out))
        await io.go(view)
        try:
            got = await wait_ranges(tap, time.monotonic_ns(), samples, RANGE_TIMEOUT_S)
        except NoFramesError:
            missed += 1
            continue
        snap = io.snapshot()
        s, head = io.s_mm(snap), snap.get("head_rad")
        if s is None or not head:
            missed += 1
            continue
        d = np.asarray(got)
        out.append(RangeSample(s, float(head[0]), float(head[1]), float(d.mean()),
                               float(d.std()), len(d)))  # fmt: skip
    return out, missed


def fit_mount(
    spec: RigSpec, samples: list[RangeSample], limits: MountThresholds | None = None
) -> MountFit:
    """Solve the mount from the samples and judge it (nothing here writes)."""
    limits = limits or MountThresholds()
    T0 = np.array(spec.rangefinder.mount.matrix)
    rig, hall = kinematics_of(spec)
    if hall is None:
        return MountFit(False, ["the rig file lists no surveyed surfaces to range against"], T0)
    got = clean_readings(spec, rig, hall, samples)
    if got.distinct < limits.min_poses:
        where = "all readings come from one pose" if got.distinct <= 1 else (
            f"readings from {got.distinct} distinct poses")  # fmt: skip
        return MountFit(False, [
            f"{where}: the mount needs ≥ {limits.min_poses} poses with clean hits, "
            "at several head angles and trolley positions"], T0, poses=got.distinct)  # fmt: skip
    used, d, sig = got.used, got.d, got.sig
    solver = RangeSolver(rig, got.hall, got.poses, d, sig, spec, FitTerms(MOUNT_AXES))
    x, J, inliers, r = robust_solve(solver, limits.min_poses)
    names = [hall.scene.surfaces[j].name for j in used]
    sv = np.linalg.svd(J, compute_uv=False)
    if sv[-1] <= RANK_RTOL * sv[0]:
        return MountFit(False, [
            "the poses do not fix the mount (its information matrix is singular): take poses "
            "at more head angles and trolley positions, against more than one surface"],
            T0, residuals_mm=r, inliers=inliers, surfaces=names, poses=got.distinct)  # fmt: skip
    chi2 = solver.chi2_dof(x, inliers)
    cov = np.linalg.inv(J.T @ J) * max(1.0, chi2)
    cov_m = cov[:5, :5]
    sigma = np.sqrt(np.diag(cov_m))
    corr = cov_m / np.outer(sigma, sigma)
    condition = float(np.linalg.cond(corr))
    delta6 = np.zeros(6)
    delta6[list(MOUNT_AXES)] = x[:5]
    T = local(T0, delta6)
    full = np.zeros((6, 6))
    full[np.ix_(MOUNT_AXES, MOUNT_AXES)] = cov_m
    full[2, 2] = spec.rangefinder.mount.cov()[2, 2]  # the roll: unobserved, as it was
    rms = float(np.sqrt(np.mean(r[inliers] ** 2)))
    rejected = float((~inliers).mean())
    reasons = []
    if rms > limits.max_rms_mm:
        reasons.append(f"RMS residual {rms:.2f} mm > {limits.max_rms_mm} mm")
    worst_mm, worst_rad = float(sigma[2:].max()), float(sigma[:2].max())
    if worst_mm > limits.max_sigma_mm:
        reasons.append(f"origin σ {worst_mm:.2f} mm > {limits.max_sigma_mm} mm")
    if 1e3 * worst_rad > limits.max_sigma_mrad:
        reasons.append(f"direction σ {1e3 * worst_rad:.2f} mrad > {limits.max_sigma_mrad} mrad")
    if condition > limits.max_condition:
        reasons.append(f"ill-conditioned: condition {condition:.0f} > {limits.max_condition:.0f}")
    if rejected > limits.max_rejected:
        reasons.append(f"{rejected:.0%} of the poses rejected as outliers")
    passed = not reasons
    if passed:
        reasons.append(
            f"mount solved from {int(inliers.sum())} poses on {len(used)} surfaces: RMS "
            f"{rms:.2f} mm, origin σ ≤ {worst_mm:.2f} mm, direction σ ≤ {1e3 * worst_rad:.2f} "
            "mrad; roll about the beam unobservable, kept"
        )
    shift = (float(x[5]), float(np.sqrt(cov[5, 5])))
    return MountFit(passed, reasons, T0, T, full, x[:5].copy(), sigma, r, inliers, names, rms,
                    chi2, condition, *shift, got.distinct)  # fmt: skip


@dataclass(frozen=True)
class Readings:
    """The samples a fit uses: those with a clean hit and a tight spread, over the surfaces
    they met (`used`: indices into the rig file's hall; `hall` holds only those)."""

    hall: Hall
    poses: Poses
    d: FloatArray  # mean readings
    sig: FloatArray  # their σ (noise / √count)
    used: list[int]
    distinct: int  # distinct poses among them


def clean_readings(spec: RigSpec, rig: Rig, hall: Hall, samples: list[RangeSample]) -> Readings:
    """Keep the samples whose beam met one surface cleanly and whose readings did not scatter
    (a spot on an edge), as the fits take them."""
    noise = spec.rangefinder.noise_mm
    kept = [
        (x, j)
        for x in samples
        if x.spread_mm <= MAX_SPREAD_FACTOR * max(noise, 0.1)
        and (j := clean_hit(rig, hall, x.s_mm, x.pan_rad, x.tilt_rad)) is not None
    ]
    distinct = {(round(x.s_mm), round(x.pan_rad, 3), round(x.tilt_rad, 3)) for x, _ in kept}
    used = sorted({j for _, j in kept})
    remap = {j: i for i, j in enumerate(used)}
    sub = Hall(hall.scene, hall.points[used], hall.normals[used], hall.sigma_mm[used])
    poses = Poses(
        np.array([x.s_mm for x, _ in kept]),
        np.array([x.pan_rad for x, _ in kept]),
        np.array([x.tilt_rad for x, _ in kept]),
        np.array([remap[j] for _, j in kept], dtype=int),
    )
    d = np.array([x.distance_mm for x, _ in kept])
    sig = np.array([max(noise, 0.05) / math.sqrt(x.count) for x, _ in kept])
    return Readings(sub, poses, d, sig, used, len(distinct))


def robust_solve(
    solver: RangeSolver, min_poses: int
) -> tuple[FloatArray, FloatArray, np.ndarray, FloatArray]:
    """Solve, drop readings off by more than OUTLIER_SIGMAS (scaled by √(χ²/dof) when above 1)
    and solve again, up to OUTLIER_ROUNDS; the solution, its whitened Jacobian, the inliers and
    every reading's residual."""
    d, sig = solver.d, solver.sig
    inliers = np.ones(len(d), dtype=bool)
    for _ in range(OUTLIER_ROUNDS):
        x, J = solver.solve(inliers)
        r = d - solver.ranges(x)
        out = np.abs(r) > OUTLIER_SIGMAS * sig * max(1.0, solver.chi2_dof(x, inliers) ** 0.5)
        new = ~out
        if np.array_equal(new, inliers) or new.sum() < min_poses:
            break
        inliers = new
    x, J = solver.solve(inliers)
    return x, J, inliers, d - solver.ranges(x)


def mount_update(fit: MountFit) -> dict[str, Any]:
    """`rangefinder.mount` for the rig file (a passing fit only)."""
    if not fit.passed or fit.T_r_l is None or fit.covariance is None:
        raise ValueError("only a passing calibration is written")
    sig = np.sqrt(np.diag(fit.covariance))
    prov = Provenance.now(
        "calibrate rangefinder (readings against the surveyed hall)",
        fit.rms_mm, "mm", int(fit.inliers.sum()), "roll about the beam unobservable: kept",
    )  # fmt: skip
    return {
        "rangefinder.mount": Pose6(
            fit.T_r_l,
            (float(sig[0]), float(sig[1]), float(sig[2])),
            (float(sig[3]), float(sig[4]), float(sig[5])),
            fit.covariance,
            prov,
        )
    }


def mount_page(fit: MountFit, limits: MountThresholds) -> Page:
    """The report page: the change with its σ, residuals per pose and per surface."""
    plt = pyplot()

    summary = fit.summary()
    pg = Page("Rangefinder mount", fit.passed, fit.reasons, limits.describe(), data=summary)
    if "table" in summary:
        pg.preformatted.append(("Mount change (local, in the mount's frame)", summary["table"]))
    if fit.T_r_l is not None:
        rows = [[f"{a:.4f}" for a in row] for row in fit.before[:3]]
        rows += [[f"{a:.4f}" for a in row] for row in fit.T_r_l[:3]]
        pg.tables.append(("T_r_l before (rows 1-3) and after (rows 4-6)",
                          ["x", "y", "z", "t (mm)"], rows))  # fmt: skip
    if len(fit.residuals_mm):
        fig, ax = plt.subplots(figsize=(11, 3.2))
        idx = np.arange(len(fit.residuals_mm))
        ax.scatter(idx[fit.inliers], fit.residuals_mm[fit.inliers], s=8, label="used")
        ax.scatter(idx[~fit.inliers], fit.residuals_mm[~fit.inliers], s=14, c="r",
                   marker="x", label="rejected")  # fmt: skip
        ax.axhline(limits.max_rms_mm, color="r", linestyle="--", linewidth=0.8)
        ax.axhline(-limits.max_rms_mm, color="r", linestyle="--", linewidth=0.8)
        ax.set_xlabel("pose")
        ax.set_ylabel("reading − prediction (mm)")
        ax.legend()
        pg.figures.append(("Residual per pose", fig))
    return pg
