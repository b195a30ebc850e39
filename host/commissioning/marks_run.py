"""`orbitar survey marks`: where each reference mark sits on the track, from the rangefinder.

The controller reports the encoder position it captured at each mark's edge (REF_MARK). For
every mark the rig file lists (nominal, from the drawing or an earlier survey) the trolley
stops `APPROACH_MM` before it, crosses it at `cross_speed` and stops `OVERSHOOT_MM` past it;
there, at rest, the rangefinder reads a surveyed surface ahead along the track and the
calibrated rig solves the arc length s_rest at which its beam reads that distance
(home_run.locate: the same model the home survey uses, so marks and home agree). The mark is
s_rest less the encoder's travel since the edge, which over a few centimetres the chain's
stretch cannot spoil. A beam across the track (|∂range/∂s| small) tells nothing and is refused.

Each mark's σ is the reading's (noise/√samples), the surface survey's and what the rig file's
mount and placement covariances put on the reading, over |∂range/∂s|, with the encoder travel's
share. The run fails on a mark whose σ exceeds the threshold, a listed mark that gave no
capture (missing) and a capture no listed mark explains (unmatched): the rig file then needs
its nominal marks fixed first. `track.marks` holds one σ for all marks: the largest is written.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.commissioning.frames import NoFramesError, RangeTap, wait_ranges
from host.commissioning.home_run import MIN_SLOPE, locate
from host.commissioning.jobs import Progress
from host.commissioning.motion import AbortedError, RigIO
from host.commissioning.plan import ViewTarget
from host.commissioning.range_model import (
    Hall,
    Poses,
    block_variance,
    clean_hits,
    kinematics_of,
    predict,
)
from host.commissioning.report import Page, pyplot, text_table
from host.geometry.head import Rig
from host.geometry.rangefinder import range_at
from host.rig import Marks, Provenance, RigSpec, travel_limits_mm

APPROACH_MM = 100.0  # where the trolley waits before crossing a mark
OVERSHOOT_MM = 40.0  # where it stops past the mark to range
CROSS_SPEED_MM_S = 100.0
MATCH_MM = 100.0  # a capture this close to a listed mark is that mark (at most 0.4 × spacing)
CHAIN_STRETCH = 0.01  # σ of the encoder's travel against the trolley's, as a fraction
ENCODER_SIGMA_MM = 0.1  # capture and count quantisation
RANGE_TIMEOUT_S = 5.0
AIM_PANS = 72
AIM_TILTS = 7
DIFF_MM = 1.0


@dataclass(frozen=True)
class MarkThresholds:
    """The stated pass/fail threshold of a marks survey."""

    max_sigma_mm: float = 2.0  # σ of every mark's arc length

    def describe(self) -> str:
        """The threshold in one line."""
        return f"σ ≤ {self.max_sigma_mm} mm for every mark; none missing, none unmatched"


@dataclass(frozen=True)
class Crossing:
    """What one mark's crossing gave: the captured edge, the rest pose and its reading."""

    index: int  # in the rig file's list
    nominal_mm: float
    edge_mm: float | None  # controller position captured at the edge (None: no capture)
    rest_mm: float  # controller position at rest, past the mark
    pan_rad: float  # measured head angles at rest
    tilt_rad: float
    distance_mm: float | None  # mean reading (None: no reading)
    count: int = 0


@dataclass(frozen=True)
class MarkResult:
    """One mark's arc length and σ (nan with a reason when it could not be measured)."""

    index: int
    nominal_mm: float
    s_mm: float = math.nan
    sigma_mm: float = math.nan
    slope: float = math.nan
    travel_mm: float = math.nan
    surface: str = ""
    problem: str = ""


def choose_aim(
    spec: RigSpec, rig: Rig, hall: Hall, s_mm: float, pan_limits: tuple[float, float],
    tilt_limits: tuple[float, float], samples: int,
) -> tuple[float, float] | None:  # fmt: skip
    """Head angles whose beam meets a surface cleanly and gives the mark the smallest σ (the
    reading's and the rig file's, over |∂range/∂s|); None when no beam reads along the track."""
    pans = np.linspace(-math.pi, math.pi, AIM_PANS, endpoint=False)
    pans = pans[(pans >= pan_limits[0]) & (pans <= pan_limits[1])]
    tilts = np.linspace(max(tilt_limits[0], 0.0), min(tilt_limits[1], math.pi / 2), AIM_TILTS)
    pan, tilt = (g.ravel() for g in np.meshgrid(pans, tilts))
    hits = clean_hits(rig, hall, np.full(pan.size, s_mm), pan, tilt)
    keep = hits >= 0
    if not keep.any():
        return None
    poses = Poses(np.full(int(keep.sum()), s_mm), pan[keep], tilt[keep], hits[keep])
    slope = predict(rig, hall, poses, ds_mm=DIFF_MM) - predict(rig, hall, poses, ds_mm=-DIFF_MM)
    slope = np.abs(slope) / (2 * DIFF_MM)
    var = (spec.rangefinder.noise_mm**2 / max(samples, 1) + hall.sigma_mm[poses.surface] ** 2
           + block_variance(spec, rig, hall, poses))  # fmt: skip
    sigma = np.where(slope >= MIN_SLOPE, np.sqrt(var) / np.maximum(slope, 1e-9), np.inf)
    best = int(np.argmin(sigma))
    if not np.isfinite(sigma[best]):
        return None
    return float(poses.pan_rad[best]), float(poses.tilt_rad[best])


def solve_mark(
    spec: RigSpec, rig: Rig, hall: Hall, home_mm: float, c: Crossing, noise_mm: float
) -> MarkResult:
    """The mark's arc length from its crossing, through the calibrated rig, with its σ."""
    base = MarkResult(c.index, c.nominal_mm)
    if c.edge_mm is None:
        return dataclasses.replace(base, problem="missing: no capture while crossing it")
    if c.distance_mm is None or c.count < 1:
        return dataclasses.replace(base, problem="no rangefinder reading at rest")
    found = locate(rig, hall.scene, c.rest_mm + home_mm, c.pan_rad, c.tilt_rad, c.distance_mm)
    if isinstance(found, str):
        return dataclasses.replace(base, problem=found)
    s_rest, slope = found
    hit = range_at(rig, hall.scene, s_rest, c.pan_rad, c.tilt_rad)
    if hit is None:
        return dataclasses.replace(base, problem="the beam meets no surveyed surface")
    poses = Poses(np.array([s_rest]), np.array([c.pan_rad]), np.array([c.tilt_rad]),
                  np.array([hit.surface]))  # fmt: skip
    reading_var = noise_mm**2 / c.count + hall.sigma_mm[hit.surface] ** 2
    var_mm = float(reading_var + block_variance(spec, rig, hall, poses)[0]) / slope**2
    travel = c.rest_mm - c.edge_mm
    var_mm += (CHAIN_STRETCH * travel) ** 2 + ENCODER_SIGMA_MM**2
    name = hall.scene.surfaces[hit.surface].name
    return dataclasses.replace(base, s_mm=s_rest - travel, sigma_mm=math.sqrt(var_mm),
                               slope=slope, travel_mm=travel, surface=name)  # fmt: skip


def match_window(nominal: tuple[float, ...]) -> float:
    """How far a capture may be from its listed mark: MATCH_MM, at most 0.4 × the spacing."""
    if len(nominal) < 2:
        return MATCH_MM
    return min(MATCH_MM, 0.4 * float(np.min(np.diff(nominal))))


def unmatched(
    captures_mm: list[float], nominal: tuple[float, ...], home_mm: float, window: float
) -> list[float]:
    """Track arc lengths of captures that no listed mark explains."""
    marks = np.asarray(nominal)
    out = []
    for p in captures_mm:
        s = p + home_mm
        if not len(marks) or float(np.min(np.abs(marks - s))) > window:
            out.append(s)
    return out


def judge(
    results: list[MarkResult], strays_mm: list[float], limits: MarkThresholds
) -> tuple[bool, list[str]]:
    """Pass when every mark was measured within the σ threshold and no capture is unexplained."""
    reasons = []
    for r in results:
        if r.problem:
            reasons.append(f"mark {r.index} (s ≈ {r.nominal_mm:.0f} mm): {r.problem}")
        elif r.sigma_mm > limits.max_sigma_mm:
            reasons.append(
                f"mark {r.index} (s ≈ {r.nominal_mm:.0f} mm): σ {r.sigma_mm:.2f} mm > "
                f"{limits.max_sigma_mm} mm"
            )
    for s in strays_mm:
        reasons.append(f"unmatched: a mark captured at s ≈ {s:.0f} mm is not in the rig file")
    if not results:
        reasons.append("the rig file lists no reference marks (add their nominal positions)")
    if reasons:
        return False, reasons
    worst = max(r.sigma_mm for r in results)
    return True, [f"{len(results)} marks surveyed, σ ≤ {worst:.2f} mm"]


async def survey_marks(
    io: RigIO, tap: RangeTap, spec: RigSpec, pan_limits: tuple[float, float],
    tilt_limits: tuple[float, float], samples: int, cross_speed: float,
    aim: tuple[float, float] | None, limits: MarkThresholds, progress: Progress,
    only: list[int] | None = None,
) -> tuple[dict[str, Any], list[MarkResult]]:  # fmt: skip
    """Cross every listed mark (or those indexed by `only`), range at rest, solve; the result
    map and the per-mark results."""
    snap = io.snapshot()
    if snap.get("position_mm") is None or snap.get("state") != "READY":
        raise AbortedError(f"the trolley must be homed and at rest (state {snap.get('state')})")
    rig, hall = kinematics_of(spec)
    if hall is None:
        raise AbortedError("the rig file lists no surveyed surfaces to range against")
    nominal = spec.track.marks.s_mm
    lo, hi = travel_limits_mm(spec.track)
    home = io.home_s_mm
    window = match_window(nominal)
    crosser = dataclasses.replace(io, speed_mm_s=cross_speed)
    t_start = time.monotonic_ns()
    results: list[MarkResult] = []
    chosen = sorted(set(range(len(nominal)) if only is None else only))
    if any(not 0 <= k < len(nominal) for k in chosen):
        raise AbortedError(f"mark indices {chosen}: the rig file lists {len(nominal)} marks")
    for i, k in enumerate(chosen):
        s_mark = nominal[k]
        progress.update(phase="crossing", view=i + 1, of=len(chosen), accepted=len(results))
        before, after = s_mark - APPROACH_MM, s_mark + OVERSHOOT_MM
        if before < lo or after > hi:
            results.append(MarkResult(k, s_mark, problem="outside the trolley's travel"))
            continue
        angles = aim or choose_aim(spec, rig, hall, after, pan_limits, tilt_limits, samples)
        if angles is None:
            results.append(MarkResult(k, s_mark, problem="no surface to range along the track"))
            continue
        await io.go(ViewTarget(before, angles[0], angles[1], f"before mark {k}"))
        t_cross = time.monotonic_ns()
        await crosser.go(ViewTarget(after, angles[0], angles[1], f"past mark {k}"))
        edges = [p for _, p in tap.marks_since(t_cross) if abs(p + home - s_mark) <= window]
        try:
            got = await wait_ranges(tap, time.monotonic_ns(), samples, RANGE_TIMEOUT_S)
        except NoFramesError:
            got = []
        snap = io.snapshot()
        head = snap.get("head_rad") or angles
        crossing = Crossing(k, s_mark, edges[0] if edges else None, float(snap["position_mm"]),
                            float(head[0]), float(head[1]),
                            float(np.mean(got)) if got else None, len(got))  # fmt: skip
        results.append(solve_mark(spec, rig, hall, home, crossing, spec.rangefinder.noise_mm))
    strays = unmatched([p for _, p in tap.marks_since(t_start)], nominal, home, window)
    ok, reasons = judge(results, strays, limits)
    return summary(ok, reasons, results, strays), results


def summary(
    ok: bool, reasons: list[str], results: list[MarkResult], strays: list[float]
) -> dict[str, Any]:
    """The op's result: verdict, per-mark numbers, the table."""
    rows: list[list[str | int | float]] = [
        [r.index, round(r.nominal_mm, 1), round(r.s_mm, 2), round(r.s_mm - r.nominal_mm, 2),
         round(r.sigma_mm, 2), round(r.slope, 2), r.surface or r.problem]
        for r in results
    ]  # fmt: skip
    header = ["mark", "listed (mm)", "surveyed (mm)", "change (mm)", "σ (mm)", "∂r/∂s", "surface"]
    return {
        "passed": ok,
        "reasons": reasons,
        "marks": [dataclasses.asdict(r) for r in results],
        "unmatched_mm": strays,
        "table": text_table(header, rows),
    }


def marks_update(
    results: list[MarkResult], samples: int, listed: Marks | None = None
) -> dict[str, Any]:
    """`track.marks` for the rig file: the surveyed arc lengths and the largest σ. With `listed`
    (the rig file's marks) a survey of some of them replaces those and keeps the others, whose
    σ then counts too."""
    if not results or any(r.problem or not math.isfinite(r.sigma_mm) for r in results):
        raise ValueError("only a complete, passing survey is written")
    by_index = {r.index: float(r.s_mm) for r in results}
    old = listed.s_mm if listed is not None else ()
    kept = [v for k, v in enumerate(old) if k not in by_index]
    s = tuple(sorted([*kept, *by_index.values()]))
    sigma = max([r.sigma_mm for r in results] + ([listed.sigma_mm] if listed and kept else []))
    prov = Provenance.now(
        "survey marks (rangefinder on a surveyed surface at rest past each capture)",
        None, "", len(results), f"{samples} readings per mark; σ is the largest of the marks'",
    )  # fmt: skip
    return {"track.marks": Marks(s, float(sigma), prov)}


def marks_page(result: dict[str, Any], limits: MarkThresholds) -> Page:
    """The report page: per-mark table and the change from the listed positions."""
    plt = pyplot()

    pg = Page("Reference marks survey", result["passed"], result["reasons"], limits.describe(),
              data=result)  # fmt: skip
    pg.preformatted.append(("Marks", result["table"]))
    ok = [m for m in result["marks"] if not m["problem"]]
    if ok:
        fig, ax = plt.subplots(figsize=(11, 3.2))
        x = [m["nominal_mm"] for m in ok]
        ax.errorbar(x, [m["s_mm"] - m["nominal_mm"] for m in ok],
                    yerr=[3 * m["sigma_mm"] for m in ok], fmt="o", capsize=3)  # fmt: skip
        ax.axhline(0.0, color="k", linewidth=0.6)
        ax.set_xlabel("listed arc length (mm)")
        ax.set_ylabel("surveyed − listed (mm), ±3σ")
        pg.figures.append(("Each mark against its listed position", fig))
    return pg
