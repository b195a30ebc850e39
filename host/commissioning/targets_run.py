"""`orbitar survey workpiece --method camera`: the workpiece frame from targets on its features.

Photogrammetry targets (a white dot in a black ring) are stuck on the model's feature points
(P1..P5 of the paper's frame, or any points whose model coordinates are known). From several
trolley stations the head aims the camera so that the targets are in view; in each frame every
target is found near where the rig file's rough workpiece pose predicts it (an intensity-weighted
centroid, sub-pixel), and each target's rays through the calibrated rig (camera, M_cr, track,
home) are intersected by least squares. The frame is the least-squares fit of the model's
points onto the triangulated ones (host.commissioning.survey.fit_frame).

Measured through the same rig the overlay is drawn with, the workpiece inherits the rig's own
errors: a focal length a little long, M_cr a little off, the track placed a little wrong or the
zero a little ahead, and the frame moves with them, so that from poses near the survey's the
overlay, which needs the camera relative to the workpiece only, hardly sees them. The frame's
error is therefore written as δp = Σ_x B_x δx + n (host.rig.with_block): B_x = ∂frame/∂x for
every calibrated block x the rays went through (intrinsics, M_cr, track placement, the zero),
by central differences of the whole triangulation and fit; n from the found pixels' σ (the
rays' misfit) through the same differences, so its shape follows the rays' geometry.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from host.commissioning.motion import RigIO
from host.commissioning.plan import ViewTarget, aim_within
from host.commissioning.report import Page, text_table
from host.commissioning.survey import WorkpieceFit, fit_frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray, invert_T, make_T, rotvec_to_R, transform_points
from host.rig import INTRINSIC_KEYS, Pose6, Provenance, RigSpec, with_block

WINDOW_PX = 40  # a target is looked for this far around its predicted pixel
EDGE_MARGIN_PX = 60  # a target predicted nearer the image edge is left for another view
BRIGHT_DN = 180  # the dot: brighter than this in every channel (model edges are orange)
RING_DN = 40  # the ring around it: weights are brightness above this
DOT_AREA_PX = (6, 400)
REFINE_RADIUS_PX = 6.0
MIN_RAYS = 2
MIN_RAY_ANGLE_RAD = math.radians(3.0)
MIN_POINTS = 3
MIN_SIGMA_PX = 0.02  # the centroid's σ is never taken as better than this
MAX_RESIDUAL_MM = 3.0
MAX_RAY_PX = 1.0  # a ray further than this from its point (reprojected) is a mismatch
# the calibrated blocks the rays go through, and the central-difference steps of their
# parameters (px and distortion; rad and mm of the local (ω, t); mm of the zero) and of a pixel
UPSTREAM_STEPS = {
    "camera.intrinsics": (1e-3,) * 5 + (1e-6,) * 5,
    "head.m_cr": (1e-6,) * 3 + (1e-3,) * 3,
    "track.placement": (1e-6,) * 3 + (1e-3,) * 3,
    "track.home": (1e-3,),
}
PIXEL_STEP = 1e-3


@dataclass
class TargetView:
    """One frame: where it was taken from and the targets found in it (index → pixel)."""

    target: ViewTarget
    wanted: tuple[int, ...]
    s_mm: float = math.nan
    head_rad: tuple[float, float] = (math.nan, math.nan)
    found: dict[int, FloatArray] = field(default_factory=dict)


@dataclass(frozen=True)
class Triangulated:
    """One target's world point, its 3×3 covariance and its rays' reprojection errors (px)."""

    index: int
    point_w: FloatArray
    covariance: FloatArray
    rays: int
    spread_rad: float
    residuals_px: FloatArray


def plan_views(
    rig: Rig, camera: CameraModel, points_w: FloatArray, stations_mm: Sequence[float],
    limits: tuple[tuple[float, float], tuple[float, float]] | None = None,
    start: tuple[float, float] | None = None,
) -> list[TargetView]:  # fmt: skip
    """Per station, as few views as keep every target well inside one of them; of the head's
    two ways to each view, the one nearer the view before (`plan.aim_within`; the first's
    nearer `start`, the head's angles now, if given)."""
    size = np.array([camera.width - 1.0, camera.height - 1.0])
    views: list[TargetView] = []
    for s in stations_mm:
        pending = list(range(len(points_w)))
        while pending:
            near = (views[-1].target.pan_rad, views[-1].target.tilt_rad) if views else start
            aim = points_w[pending].mean(axis=0)
            angles = aim_within(rig, camera, s, aim, size / 2, limits, near)
            inside = [] if angles is None else _inside(rig, camera, s, angles, points_w, pending)
            if len(inside) < len(pending):  # not all at once: centre the first one left
                angles = aim_within(rig, camera, s, points_w[pending[0]], size / 2, limits, near)
                inside = (
                    [] if angles is None else _inside(rig, camera, s, angles, points_w, pending)
                )
            if angles is None or not inside:
                pending.pop(0)  # cannot be seen from here
                continue
            label = f"s={s:.0f} " + ",".join(f"T{i + 1}" for i in inside)
            views.append(TargetView(ViewTarget(float(s), *angles, label), tuple(inside)))
            pending = [i for i in pending if i not in inside]
    return views


def _inside(
    rig: Rig, camera: CameraModel, s: float, angles: tuple[float, float], points_w: FloatArray,
    which: Sequence[int],
) -> list[int]:  # fmt: skip
    """The targets predicted inside the image, away from its edge."""
    uv, valid = camera.project(transform_points(rig.T_c_w(s, *angles), points_w[list(which)]))
    lo = EDGE_MARGIN_PX
    ok = valid & (uv[:, 0] > lo) & (uv[:, 0] < camera.width - 1 - lo)
    ok &= (uv[:, 1] > lo) & (uv[:, 1] < camera.height - 1 - lo)
    return [i for i, good in zip(which, ok, strict=True) if good]


def find_target(
    image: np.ndarray, uv0: FloatArray, window_px: int = WINDOW_PX
) -> FloatArray | None:
    """The dot nearest to uv0 within the window: intensity-weighted centroid (sub-pixel)."""
    h, w = image.shape[:2]
    if not np.all(np.isfinite(uv0)):
        return None
    u0, v0 = round(float(uv0[0])), round(float(uv0[1]))
    x0, x1 = max(0, u0 - window_px), min(w, u0 + window_px + 1)
    y0, y1 = max(0, v0 - window_px), min(h, v0 + window_px + 1)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    patch = image[y0:y1, x0:x1]
    grey = patch.min(axis=2) if patch.ndim == 3 else patch
    mask = (grey > BRIGHT_DN).astype(np.uint8)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    best, best_d = None, math.inf
    for k in range(1, n):
        area = int(stats[k, cv2.CC_STAT_AREA])
        if not DOT_AREA_PX[0] <= area <= DOT_AREA_PX[1]:
            continue
        d = float(np.hypot(centroids[k][0] + x0 - uv0[0], centroids[k][1] + y0 - uv0[1]))
        if d < best_d:
            best, best_d = centroids[k], d
    if best is None:
        return None
    c = np.array([best[0], best[1]], dtype=np.float64)
    yy, xx = np.mgrid[0 : grey.shape[0], 0 : grey.shape[1]]
    weight = np.clip(grey.astype(np.float64) - RING_DN, 0.0, None)
    for _ in range(3):  # refine over a disc around the estimate: the dot and its soft edge
        near = np.hypot(xx - c[0], yy - c[1]) <= REFINE_RADIUS_PX
        wsum = float(weight[near].sum())
        if wsum <= 0.0:
            return None
        c = np.array([(weight * xx)[near].sum() / wsum, (weight * yy)[near].sum() / wsum])
    return c + np.array([x0, y0], dtype=np.float64)


async def capture(
    io: RigIO, views: Sequence[TargetView], rig: Rig, camera: CameraModel, points_w: FloatArray,
    progress: dict[str, Any],
) -> list[TargetView]:  # fmt: skip
    """Visit each view, take a frame at rest, find its targets near their predicted pixels."""
    for i, view in enumerate(views):
        progress.update(phase="capturing", view=i + 1, of=len(views), label=view.target.label)
        await io.go(view.target)
        frame = await io.grab()
        snap = io.snapshot()
        s_mm = io.s_mm(snap)
        view.s_mm = math.nan if s_mm is None else s_mm
        view.head_rad = io.head_at_rest(snap)
        T_c_w = rig.T_c_w(view.s_mm, *view.head_rad)
        uv, _ = camera.project(transform_points(T_c_w, points_w[list(view.wanted)]))
        found = await asyncio.to_thread(_find_all, frame.image, uv)
        view.found = {k: p for k, p in zip(view.wanted, found, strict=True) if p is not None}
        progress.update(found=sum(len(v.found) for v in views[: i + 1]))
    return list(views)


def _find_all(image: np.ndarray, uv: FloatArray) -> list[FloatArray | None]:
    return [find_target(image, p) for p in uv]


def triangulate(
    views: Sequence[TargetView], rig: Rig, camera: CameraModel, count: int
) -> tuple[list[Triangulated], float]:
    """Each target seen in ≥ 2 views at an angle; the pixel σ the rays' misfit implies."""
    rays: dict[int, list[tuple[FloatArray, FloatArray, FloatArray, FloatArray]]] = {}
    sightings = [
        (k, uv, rig.T_w_c(v.s_mm, *v.head_rad))
        for v in views
        if np.isfinite([v.s_mm, *v.head_rad]).all()
        for k, uv in v.found.items()
    ]
    if sightings:  # one undistortion for all (elementwise: the same as one at a time)
        xys = camera.undistort_normalized(np.array([uv for _, uv, _ in sightings]))
    for (k, uv, T_w_c), xy in zip(sightings, xys if sightings else [], strict=True):
        d = T_w_c[:3, :3] @ np.array([xy[0], xy[1], 1.0])
        rays.setdefault(k, []).append((T_w_c[:3, 3], d / np.linalg.norm(d), uv, T_w_c))
    points: list[tuple[int, FloatArray, FloatArray, float, FloatArray]] = []
    for k in range(count):
        got = rays.get(k, [])
        if len(got) < MIN_RAYS:
            continue
        dirs = np.array([d for _, d, _, _ in got])
        spread = float(np.arccos(np.clip(np.min(dirs @ dirs.T), -1.0, 1.0)))
        if spread < MIN_RAY_ANGLE_RAD:
            continue
        A = np.zeros((3, 3))
        first = _intersect(got, np.ones(len(got)))
        weights = []
        for c, _, _, _ in got:  # a ray's lateral σ grows with the distance along it
            weights.append(1.0 / float(np.linalg.norm(first - c)) ** 2)
        X = _intersect(got, np.array(weights))
        for (_, d, _, _), wgt in zip(got, weights, strict=True):
            A += wgt * (np.eye(3) - np.outer(d, d))
        res = []
        for _, _, uv, T_w_c in got:
            pred, _ = camera.project(transform_points(invert_T(T_w_c), X[None, :]))
            res.append(pred[0] - uv)
        points.append((k, X, np.asarray(np.linalg.inv(A), np.float64), spread, np.array(res)))
    n_res = sum(2 * len(p[4]) for p in points)
    dof = n_res - 3 * len(points)
    sq = sum(float(np.sum(p[4] ** 2)) for p in points)
    sigma_px = max(math.sqrt(sq / dof) if dof > 0 else math.nan, MIN_SIGMA_PX)
    if not math.isfinite(sigma_px):
        sigma_px = 10 * MIN_SIGMA_PX  # two rays per point leave one residual: be careful
    # the information above is in 1/mm² per unit angle: scale by the angular σ of a ray
    ang = sigma_px / camera.fx
    out = [
        Triangulated(k, X, cov * ang * ang, len(r), spread, r) for k, X, cov, spread, r in points
    ]
    return out, sigma_px


def _intersect(
    rays: Sequence[tuple[FloatArray, FloatArray, FloatArray, FloatArray]], weights: FloatArray
) -> FloatArray:
    """The point nearest to all rays (weighted squared distances)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for (c, d, _, _), w in zip(rays, weights, strict=True):
        P = np.eye(3) - np.outer(d, d)
        A += w * P
        b += w * P @ c
    out: FloatArray = np.asarray(np.linalg.solve(A, b), dtype=np.float64)
    return out


@dataclass
class CameraSurvey:
    """Verdict, the triangulated targets, the fit and the frame's covariance."""

    passed: bool
    reasons: list[str]
    views: list[TargetView]
    points: list[Triangulated]
    sigma_px: float = math.nan
    fit: WorkpieceFit | None = None
    covariance: FloatArray | None = None  # absolute: the rig's errors carried in, and the noise
    # ∂(frame's local error)/∂(each calibrated block's): the survey moves with the rig it used
    depends: dict[str, FloatArray] = field(default_factory=dict)
    noise: FloatArray | None = None  # the found pixels' share (6×6)

    def summary(self) -> dict[str, Any]:
        """Plain values for the status op and the report."""
        rows: list[list[str | float]] = []
        for p in self.points:
            sd = float(np.sqrt(np.trace(p.covariance) / 3))
            err = float(np.sqrt(np.mean(np.sum(p.residuals_px**2, axis=1))))
            xyz = [round(float(x), 2) for x in p.point_w]
            rows.append([f"T{p.index + 1}", p.rays, round(math.degrees(p.spread_rad), 1),
                         round(err, 3), round(sd, 3), *xyz])  # fmt: skip
        head = ["target", "rays", "spread °", "ray RMS px", "σ mm", "x", "y", "z"]
        out: dict[str, Any] = {
            "passed": self.passed, "reasons": self.reasons, "method": "camera",
            "views": len(self.views), "found": sum(len(v.found) for v in self.views),
            "sigma_px": self.sigma_px, "table": text_table(head, rows),
        }  # fmt: skip
        if self.fit is not None and self.covariance is not None:
            out.update(T_w_p=self.fit.T_w_p.tolist(), covariance=self.covariance.tolist(),
                       residuals_mm=self.fit.residuals_mm.round(3).tolist(),
                       rms_mm=self.fit.rms_mm)  # fmt: skip
        return out


def judge(
    views: list[TargetView], rig: Rig, camera: CameraModel, model_p: FloatArray, spec: RigSpec
) -> CameraSurvey:
    """Triangulate, fit the model's points, and judge (never raises on bad data); `rig` and
    `camera` are `spec`'s, whose covariances the frame's takes in."""
    points, sigma_px = triangulate(views, rig, camera, len(model_p))
    out = CameraSurvey(False, [], views, points, sigma_px)
    if len(points) < MIN_POINTS:
        seen = sum(len(v.found) for v in views)
        out.reasons = [
            f"{len(points)} targets triangulated (≥ {MIN_RAYS} rays at ≥ "
            f"{math.degrees(MIN_RAY_ANGLE_RAD):.0f}°), need ≥ {MIN_POINTS}; {seen} sightings "
            f"in {len(views)} views"
        ]
        return out
    bad = [p for p in points if np.max(np.linalg.norm(p.residuals_px, axis=1)) > MAX_RAY_PX]
    if bad:
        which = ", ".join(f"T{p.index + 1}" for p in bad)
        out.reasons = [f"rays of {which} miss their point by > {MAX_RAY_PX} px (a wrong dot?)"]
        return out
    P = np.array([p.point_w for p in points])
    X = model_p[[p.index for p in points]]
    sigma_mm = float(np.sqrt(np.mean([np.max(np.linalg.eigvalsh(p.covariance)) for p in points])))
    try:
        fit = fit_frame(P, X, sigma_mm)
    except ValueError as exc:
        out.reasons = [str(exc)]
        return out
    out.fit = fit
    out.depends, out.noise = sensitivities(views, rig, camera, model_p, fit.T_w_p, sigma_px)
    out.covariance, _ = with_block(
        spec, "workpiece.frame", out.noise, Provenance(), depends=out.depends
    )
    if fit.rms_mm > MAX_RESIDUAL_MM:
        why = f"fit RMS {fit.rms_mm:.2f} mm > {MAX_RESIDUAL_MM} mm (a target off its point?)"
        out.reasons = [why]
        return out
    out.passed = True
    out.reasons = [
        f"workpiece frame from {len(points)} targets in {len(views)} views: fit RMS "
        f"{fit.rms_mm:.3f} mm, rays {sigma_px:.3f} px"
    ]
    return out


def sensitivities(
    views: Sequence[TargetView], rig: Rig, camera: CameraModel, model_p: FloatArray,
    T_w_p: FloatArray, sigma_px: float,
) -> tuple[dict[str, FloatArray], FloatArray]:  # fmt: skip
    """∂(frame's local error)/∂(each UPSTREAM block, in the budget's conventions), and the
    noise covariance of σ_px on every found pixel, by central differences of the survey."""

    def frame(vs: Sequence[TargetView], r: Rig, c: CameraModel) -> FloatArray:
        pts, _ = triangulate(vs, r, c, len(model_p))
        T = fit_frame(np.array([p.point_w for p in pts]), model_p[[p.index for p in pts]], 1.0)
        D = invert_T(T_w_p) @ T.T_w_p
        R = D[:3, :3]
        w = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
        return np.concatenate([w, D[:3, 3]])

    Variant = tuple[Sequence[TargetView], Rig, CameraModel]

    def central(make: Callable[[float], Variant], h: float) -> FloatArray:
        out: FloatArray = (frame(*make(h)) - frame(*make(-h))) / (2 * h)
        return out

    def upstream(name: str, j: int, h: float) -> Variant:
        """The views and rig with parameter j of block `name` off by h."""
        if name == "camera.intrinsics":
            key = INTRINSIC_KEYS[j]
            return views, rig, dataclasses.replace(camera, **{key: getattr(camera, key) + h})
        if name == "head.m_cr":
            return views, dataclasses.replace(rig, T_r_c=rig.T_r_c @ _step(j, h)), camera
        if name == "track.placement":
            track = dataclasses.replace(rig.track, T_w_track=rig.track.T_w_track @ _step(j, h))
            return views, dataclasses.replace(rig, track=track), camera
        return [dataclasses.replace(v, s_mm=v.s_mm + h) for v in views], rig, camera  # the zero

    def nudged(i: int, k: int, axis: int, h: float) -> Variant:
        """The views with one found pixel off by h along one axis."""
        uv = views[i].found[k].copy()
        uv[axis] += h
        moved = dataclasses.replace(views[i], found={**views[i].found, k: uv})
        return [*views[:i], moved, *views[i + 1 :]], rig, camera

    depends = {
        name: np.column_stack([
            central(functools.partial(upstream, name, j), step) for j, step in enumerate(steps)
        ])
        for name, steps in UPSTREAM_STEPS.items()
    }  # fmt: skip
    noise = np.zeros((6, 6))
    for i, v in enumerate(views):
        for k in v.found:
            for axis in (0, 1):
                col = central(functools.partial(nudged, i, k, axis), PIXEL_STEP)
                noise += sigma_px**2 * np.outer(col, col)
    return depends, noise


def _step(j: int, h: float) -> FloatArray:
    """exp of a step h along local axis j (ω 0-2, t 3-5)."""
    d = np.zeros(6)
    d[j] = h
    out: FloatArray = make_T(rotvec_to_R(d[:3]), d[3:])
    return out


def workpiece_update(out: CameraSurvey, spec: RigSpec) -> dict[str, Any]:
    """`workpiece.frame` for the rig file, and the joint covariance with its cross terms.

    The frame was triangulated through the rig of `spec`, so it shares its errors: written as
    independent, the budget would count them twice (a workpiece surveyed through the rig and
    the camera drawing it move together, and the overlay hardly sees it).
    """
    if not out.passed or out.fit is None or out.noise is None:
        raise ValueError("only a passing survey is written")
    prov = Provenance.now(
        "survey workpiece (camera, targets on the feature points)", out.fit.rms_mm, "mm",
        len(out.views),
    )  # fmt: skip
    cov, joint = with_block(spec, "workpiece.frame", out.noise, prov, depends=out.depends)
    d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    rad, mm = (float(d[0]), float(d[1]), float(d[2])), (float(d[3]), float(d[4]), float(d[5]))
    frame = Pose6(out.fit.T_w_p, rad, mm, cov, prov)
    return {"workpiece.frame": frame, "covariance": joint}


def page(out: CameraSurvey) -> Page:
    """The report page."""
    result = out.summary()
    pg = Page(
        "Workpiece survey (camera)", out.passed, out.reasons,
        f"≥ {MIN_POINTS} targets, rays within {MAX_RAY_PX} px, fit RMS ≤ {MAX_RESIDUAL_MM} mm",
        data=result,
    )  # fmt: skip
    pg.preformatted.append(("Targets", result["table"]))
    return pg
