"""`orbitar calibrate intrinsics`: capture board views along a plan, solve the lens, judge it.

The run visits every planned view, takes a frame once the rig is still and keeps it when the
board is found with enough corners and sharp edges (a blurred view is visited again at the end,
up to `RETAKES` times, then refused). The lens is solved with skew and σ
(host.calibration.intrinsics), outlier views dropped by their RMS. The verdict passes only if
enough views were kept, they cover the image in X, Y, size and skew, the RMS is within the
threshold and the σ are as small as `Thresholds` asks; only then may the result be written.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.calibration.board import BoardDetector, Detection
from host.calibration.intrinsics import IntrinsicsResult, calibrate_with_rejection
from host.commissioning import coverage
from host.commissioning.head_noise import angle_noise_update
from host.commissioning.motion import RigIO
from host.commissioning.plan import ViewTarget
from host.commissioning.report import Page, per_view_figure, residual_figure, text_table
from host.geometry.camera import CameraModel
from host.geometry.transforms import FloatArray
from host.rig import INTRINSIC_KEYS, Intrinsics, Provenance

RETAKES = 2


@dataclass(frozen=True)
class Thresholds:
    """What a passing intrinsics calibration must reach (stated in the verdict)."""

    max_rms_px: float = 0.5
    min_views: int = 10
    max_rel_sigma_focal: float = 2e-3  # σ(fx)/fx, σ(fy)/fy
    max_sigma_centre_px: float = 2.0  # σ(u0), σ(v0)

    def text(self) -> str:
        """One line for the verdict."""
        return (
            f"RMS ≤ {self.max_rms_px} px, ≥ {self.min_views} views, σ(f)/f ≤ "
            f"{self.max_rel_sigma_focal:g}, σ(u0, v0) ≤ {self.max_sigma_centre_px} px, coverage "
            + ", ".join(f"{k} ≥ {v}" for k, v in coverage.MIN_PROGRESS.items())
        )


@dataclass
class CapturedView:
    """One planned view and what came of it."""

    target: ViewTarget
    status: str  # "ok", "blurred", "not found"
    detection: Detection | None = None
    cover: coverage.ViewCoverage | None = None
    attempts: int = 0
    s_mm: float = float("nan")  # where the host saw the trolley and the head at the frame
    head_rad: tuple[float, float] = (float("nan"), float("nan"))
    # the head's readings (n, 2) while it stood for the frame (its read noise is measured)
    rest_head_rad: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass
class Outcome:
    """Verdict, reasons, the solution (if any) and what the views were."""

    passed: bool
    reasons: list[str]
    views: list[CapturedView]
    result: IntrinsicsResult | None = None
    nominal: CameraModel | None = None
    progress: dict[str, float] = field(default_factory=dict)

    def table(self) -> str:
        """The short terminal table: parameter, nominal, calibrated, σ."""
        return text_table(["param", "nominal", "calibrated", "sigma"], self.rows())

    def rows(self) -> list[list[str | float]]:
        """Rows of the parameter table."""
        if self.result is None or self.nominal is None:
            return []
        cam, std = self.result.camera, self.result.std
        return [[k, getattr(self.nominal, k), getattr(cam, k), std[k]] for k in self.result.keys]

    def summary(self) -> dict[str, Any]:
        """Plain values for the status op and results.json."""
        counts = {s: sum(v.status == s for v in self.views) for s in ("ok", "blurred", "not found")}
        out: dict[str, Any] = {
            "passed": self.passed,
            "reasons": self.reasons,
            "views": counts,
            "coverage": self.progress,
            "table": self.table(),
        }
        if self.result is not None:
            r = self.result
            out["camera"] = r.camera.to_config()
            out["sigma"] = r.std
            out["rms_px"] = r.rms_px
            out["opencv_rms_px"] = r.opencv_rms_px
            out["per_view_rms_px"] = [round(float(e), 4) for e in r.per_view_rms_px]
            out["rejected_views"] = list(r.rejected_views)
        return out


async def capture(
    io: RigIO,
    plan: Sequence[ViewTarget],
    detector: BoardDetector,
    nominal: CameraModel,
    progress: dict[str, Any],
) -> list[CapturedView]:
    """Visit the plan's views and keep the sharp ones; progress shows counts and coverage.

    A view's frame is searched for the board while the rig goes on to the next view (the
    search takes a good part of a head move); the views found blurred are visited again at the
    end, up to `RETAKES` times. A board out of view stays out of view: it is not retaken.
    """
    views = [CapturedView(target, "not found") for target in plan]
    for attempt in range(1, RETAKES + 2):
        todo = [v for v in views if v.status == "blurred"] if attempt > 1 else views
        searches: list[asyncio.Task[None]] = []
        try:
            for i, view in enumerate(todo):
                label = view.target.label + (" (retake)" if attempt > 1 else "")
                progress.update(phase="capturing", view=i + 1, of=len(todo), label=label)
                await io.go(view.target)
                frame = await io.grab()
                snap = io.snapshot()
                s_mm = io.s_mm(snap)
                view.s_mm = float("nan") if s_mm is None else s_mm
                view.head_rad = io.head_at_rest(snap)
                view.rest_head_rad = io.rest_head_rad
                search = _search(view, frame.image, attempt, detector, nominal)
                searches.append(asyncio.create_task(search))
                searches[-1].add_done_callback(lambda _: _show(views, progress))
            await asyncio.gather(*searches)
        finally:
            for task in searches:
                task.cancel()
    return views


async def _search(
    view: CapturedView, image: np.ndarray, attempt: int, detector: BoardDetector,
    nominal: CameraModel,
) -> None:  # fmt: skip
    """Find the board in a view's frame (in a worker thread) and judge its sharpness."""
    det = await asyncio.to_thread(detector.detect, image)
    view.attempts = attempt
    if det is None:
        view.status = "not found"
        return
    view.detection = det
    view.status = "ok" if det.sharp else "blurred"
    if det.sharp:
        view.cover = coverage.view_coverage(det.object_points, det.image_points, nominal)


def _show(views: list[CapturedView], progress: dict[str, Any]) -> None:
    """Counts, coverage and per-view errors of the views searched so far."""
    searched = [v for v in views if v.attempts]
    kept = [v.cover for v in searched if v.cover is not None]
    progress.update(
        accepted=len(kept),
        blurred=sum(v.status == "blurred" for v in searched),
        not_found=sum(v.status == "not found" for v in searched),
        coverage=coverage.progress(kept),
        view_errors=[view_error(v) for v in searched],
    )


def view_error(view: CapturedView) -> dict[str, Any]:
    """A captured view for the live progress: its status and its PnP RMS (px) if kept."""
    rms = view.cover.rms_px if view.cover is not None else float("nan")
    return {"label": view.target.label, "status": view.status,
            "rms_px": round(rms, 4) if np.isfinite(rms) else None}  # fmt: skip


def judge(
    views: list[CapturedView],
    nominal: CameraModel,
    limits: Thresholds,
    full_distortion: bool = False,
) -> Outcome:
    """Solve from the kept views and give the verdict (never raises on bad data)."""
    kept = [v for v in views if v.status == "ok" and v.detection is not None]
    prog = coverage.progress([v.cover for v in kept if v.cover is not None])
    blurred = sum(v.status == "blurred" for v in views)
    missing = sum(v.status == "not found" for v in views)
    if len(kept) < limits.min_views:
        why = (
            f"too few views: {len(kept)} kept of {len(views)} planned ({blurred} blurred, "
            f"{missing} without the board), need ≥ {limits.min_views}"
        )
        return Outcome(False, [why], views, None, nominal, prog)
    short = coverage.shortfall(prog)
    if short:
        why = "degenerate views: " + "; ".join(short) + " (widen the plan: more stations, tilt)"
        return Outcome(False, [why], views, None, nominal, prog)
    dets = [v.detection for v in kept if v.detection is not None]
    try:
        res = calibrate_with_rejection(
            [d.object_points for d in dets],
            [d.image_points for d in dets],
            nominal.size,
            full_distortion,
        )
    except (ValueError, np.linalg.LinAlgError) as exc:
        return Outcome(False, [f"the solve failed: {exc}"], views, None, nominal, prog)
    return Outcome(*_checks(res, limits), views, res, nominal, prog)


def _checks(res: IntrinsicsResult, limits: Thresholds) -> tuple[bool, list[str]]:
    """The threshold checks; reasons name each one that failed (or summarise the pass)."""
    cam, std, bad = res.camera, res.std, []
    if res.rms_px > limits.max_rms_px:
        bad.append(f"RMS {res.rms_px:.3f} px > {limits.max_rms_px} px")
    for key in ("fx", "fy"):
        rel = std[key] / getattr(cam, key)
        if rel > limits.max_rel_sigma_focal:
            bad.append(f"σ({key})/{key} = {rel:.2e} > {limits.max_rel_sigma_focal:g}")
    for key in ("u0", "v0"):
        if std[key] > limits.max_sigma_centre_px:
            bad.append(f"σ({key}) = {std[key]:.2f} px > {limits.max_sigma_centre_px} px")
    kept = len(res.per_view_rms_px)
    if kept < limits.min_views:
        bad.append(f"only {kept} views left after dropping outliers, need ≥ {limits.min_views}")
    if bad:
        return False, bad
    dropped = f", {len(res.rejected_views)} outlier views dropped" if res.rejected_views else ""
    return True, [f"RMS {res.rms_px:.3f} px over {kept} views{dropped}"]


def rig_update(outcome: Outcome) -> dict[str, Any]:
    """The rig-file blocks a passing run writes: `camera.intrinsics` with σ, covariance, origin,
    and `head.angle_noise` measured from the head's readings at the views' rests (the error
    budget and `calibrate head` use it; the datasheet's stays with too few readings)."""
    res = outcome.result
    if res is None or not outcome.passed:
        raise ValueError("only a passing calibration is written")
    values = tuple(float(getattr(res.camera, k)) for k in INTRINSIC_KEYS)
    idx = [INTRINSIC_KEYS.index(k) for k in res.keys]
    cov = np.zeros((len(INTRINSIC_KEYS), len(INTRINSIC_KEYS)))
    cov[np.ix_(idx, idx)] = res.covariance
    sigma = tuple(float(np.sqrt(cov[i, i])) for i in range(len(INTRINSIC_KEYS)))
    views = len(res.per_view_rms_px)
    prov = Provenance.now("calibrate intrinsics (ChArUco, skew refined)", res.rms_px, "px", views)
    cov_t = tuple(tuple(float(x) for x in row) for row in cov)
    rests = [v.rest_head_rad for v in outcome.views if len(v.rest_head_rad)]
    return {
        "camera.intrinsics": Intrinsics(values, sigma, cov_t, prov),
        **angle_noise_update(rests, len(rests)),
    }


def page(outcome: Outcome, limits: Thresholds) -> Page:
    """The report page: verdict, table, coverage, per-view errors and residual plots."""
    pg = Page(
        "Camera intrinsics", outcome.passed, outcome.reasons, limits.text(), data=outcome.summary()
    )
    pg.preformatted.append(
        ("Coverage (as ROS camera_calibration)", coverage.bars(outcome.progress))
    )
    if outcome.result is not None:
        pg.tables.append(
            (
                "Parameters: nominal (before) and calibrated (after)",
                ["param", "nominal", "calibrated", "σ"],
                outcome.rows(),
            )
        )
    pg.tables.append(
        (
            "Views",
            ["#", "view", "status", "corners", "edge width px", "RMS px"],
            _view_rows(outcome),
        )
    )
    res = outcome.result
    if res is not None:
        kept = [v for v in outcome.views if v.status == "ok" and v.detection is not None]
        used = [v for i, v in enumerate(kept) if i not in res.rejected_views]
        uv = np.concatenate([v.detection.image_points for v in used if v.detection is not None])
        pg.figures.append(
            ("Residuals", residual_figure(uv, np.concatenate(res.residuals_px), res.camera.size))
        )
        pg.figures.append(
            (
                "Per-view RMS",
                per_view_figure(
                    [v.target.label for v in used], list(res.per_view_rms_px), limits.max_rms_px
                ),
            )
        )
    return pg


def _view_rows(outcome: Outcome) -> list[list[str | int | float]]:
    """One row per planned view (RMS for those that entered the solve)."""
    rms: dict[int, float] = {}
    res = outcome.result
    if res is not None:
        kept = [i for i, v in enumerate(outcome.views) if v.status == "ok"]
        used = [k for j, k in enumerate(kept) if j not in res.rejected_views]
        rms = {k: float(e) for k, e in zip(used, res.per_view_rms_px, strict=True)}
        for j in res.rejected_views:
            rms[kept[j]] = float("nan")
    rows: list[list[str | int | float]] = []
    for i, v in enumerate(outcome.views):
        det = v.detection
        status = "outlier" if i in rms and np.isnan(rms[i]) else v.status
        rows.append([i + 1, v.target.label, status, det.count if det else 0,
                     round(det.edge_width_px, 2) if det else "", round(rms[i], 3) if i in rms and not np.isnan(rms[i]) else ""])  # noqa: E501  # fmt: skip
    return rows
