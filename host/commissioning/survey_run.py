"""`orbitar survey workpiece`: the workpiece frame from rangefinder readings of its features.

The installer gives, per feature point, where the trolley stands and the head angles that put
the rangefinder's beam on it (picked in the camera view, or known). For each the rig goes there,
comes to rest and averages `samples` readings; the point is the beam's end, through the rig as
calibrated (track, head, rangefinder mount T_r_l). Three points make the paper's frame (P1, P3,
P5 in that order); more, with the model's own coordinates of the same features, a least-squares
fit with residuals (host.commissioning.survey). Writes `workpiece.frame` with its covariance.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.commissioning.frames import RangeTap, wait_ranges
from host.commissioning.motion import RigIO
from host.commissioning.plan import ViewTarget
from host.commissioning.report import Page, text_table
from host.commissioning.survey import WorkpieceFit, fit_frame, frame_from_three
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray
from host.rig import Pose6, Provenance

RANGE_TIMEOUT_S = 5.0
MAX_RESIDUAL_MM = 3.0


@dataclass(frozen=True)
class SurveyedPoint:
    """One feature: where it was aimed from, the mean reading, its spread, the world point."""

    aim: ViewTarget
    range_mm: float
    spread_mm: float
    point_w: FloatArray


async def measure(
    io: RigIO, tap: RangeTap, rig: Rig, aims: Sequence[ViewTarget], samples: int,
    progress: dict[str, Any],
) -> list[SurveyedPoint]:  # fmt: skip
    """Aim, settle, average readings, and place each point through the calibrated rig."""
    out = []
    for i, aim in enumerate(aims):
        progress.update(phase="ranging", view=i + 1, of=len(aims), label=aim.label)
        await io.go(aim)
        readings = await wait_ranges(tap, time.monotonic_ns(), samples, RANGE_TIMEOUT_S)
        snap = io.snapshot()
        s_mm = io.s_mm(snap)
        head = snap.get("head_rad") or (aim.pan_rad, aim.tilt_rad)
        d = float(np.mean(readings))
        T_w_l = (
            rig.T_w_r(aim.s_mm if s_mm is None else s_mm, float(head[0]), float(head[1]))
            @ rig.T_r_l
        )
        point = T_w_l[:3, 3] + T_w_l[:3, 2] * d
        out.append(SurveyedPoint(aim, d, float(np.std(readings)), point))
        progress["view_errors"] = [
            {"label": p.aim.label, "status": "ok", "spread_mm": round(p.spread_mm, 3)} for p in out
        ]
    return out


def judge(
    points: list[SurveyedPoint], model_p: FloatArray | None, sigma_mm: float
) -> tuple[bool, list[str], WorkpieceFit | None]:
    """The frame and the verdict (never raises on bad data)."""
    P = np.array([p.point_w for p in points])
    try:
        if model_p is not None:
            fit = fit_frame(P, model_p, sigma_mm)
        elif len(P) == 3:
            fit = frame_from_three(P[0], P[1], P[2], sigma_mm)
        else:
            return (
                False,
                [f"{len(P)} points without model_points_mm: give P1, P3, P5 or the model's"],
                None,
            )
    except ValueError as exc:
        return False, [str(exc)], None
    if model_p is not None and fit.rms_mm > MAX_RESIDUAL_MM:
        return (
            False,
            [f"fit RMS {fit.rms_mm:.2f} mm > {MAX_RESIDUAL_MM} mm (a point off its feature?)"],
            fit,
        )
    what = (
        f"fit RMS {fit.rms_mm:.2f} mm over {len(P)} points" if model_p is not None else "P1, P3, P5"
    )
    return True, [f"workpiece frame from {what}"], fit


def summary(
    ok: bool, reasons: list[str], points: list[SurveyedPoint], fit: WorkpieceFit | None
) -> dict[str, Any]:
    """Plain values for the status op and the report."""
    rows: list[list[str | float]] = []
    for p in points:
        xyz = [round(float(x), 2) for x in p.point_w]
        rows.append([p.aim.label, round(p.range_mm, 2), round(p.spread_mm, 2), *xyz])
    out: dict[str, Any] = {"passed": ok, "reasons": reasons,
                           "table": text_table(["point", "range mm", "spread mm", "x", "y", "z"], rows)}  # noqa: E501  # fmt: skip
    if fit is not None:
        out.update(T_w_p=fit.T_w_p.tolist(), covariance=fit.covariance.tolist(),
                   residuals_mm=fit.residuals_mm.round(3).tolist(), rms_mm=fit.rms_mm)  # fmt: skip
    return out


def workpiece_update(fit: WorkpieceFit, n: int) -> dict[str, Any]:
    """`workpiece.frame` for the rig file."""
    d = np.sqrt(np.clip(np.diag(fit.covariance), 0.0, None))
    prov = Provenance.now("survey workpiece (rangefinder)", fit.rms_mm, "mm", n)
    rad, mm = (float(d[0]), float(d[1]), float(d[2])), (float(d[3]), float(d[4]), float(d[5]))
    return {"workpiece.frame": Pose6(fit.T_w_p, rad, mm, fit.covariance, prov)}


def page(result: dict[str, Any]) -> Page:
    """The report page."""
    pg = Page(
        "Workpiece survey",
        result["passed"],
        result["reasons"],
        f"fit RMS ≤ {MAX_RESIDUAL_MM} mm",
        data=result,
    )
    pg.preformatted.append(("Points", result["table"]))
    return pg


def point_sigma_mm(noise_mm: float, samples: int) -> float:
    """σ of an averaged reading along the beam (the aim's lateral error is the installer's)."""
    return noise_mm / math.sqrt(max(samples, 1))
