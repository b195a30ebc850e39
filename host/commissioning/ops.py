"""The commissioning operations of the control socket (docs/COMMISSIONING.md).

`calibrate_intrinsics` (and the other calibrations) start a run in the daemon and return its id
at once; `commissioning_status` shows its progress (views, coverage bars) and, when it is over,
its verdict and result; `commissioning_cancel` ends it, as any STOP or ESTOP does. Arguments are
checked before anything moves, with the key named in the error. `COMMISSIONING_OPS` joins
host.control.ops.OPS.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from host.calibration.board import BoardDetector, BoardSpec
from host.commissioning import (
    head_run,
    home_run,
    intrinsics_run,
    latency_run,
    marks_run,
    rangefinder_run,
    survey_run,
    targets_run,
    track_run,
)
from host.commissioning.env import CommissioningEnv
from host.commissioning.frames import FrameTap
from host.commissioning.jobs import Filmed, JobBusyError, Progress
from host.commissioning.motion import TRAVEL_SPEED_MM_S, AbortedError, RigIO
from host.commissioning.plan import IMAGE_TARGETS, ViewTarget, aim_within, board_plan, sweep
from host.commissioning.report import Page, run_dir, write_page
from host.control.ops import MAX_SPEED_MM_S, Handler, OpContext, OpError, Role, number
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray, transform_points
from host.rig import update_rig

MAX_STATIONS = 64
MAX_POSES = 512
MAX_TARGETS = 25
MAX_ABS_MM = 1e6
# views reused by a later run: same stations and zero to this, the board's centre to this
REUSE_TOL_MM = 1e-3
REUSE_CENTRE_MM = 100.0


def env_of(ctx: OpContext) -> CommissioningEnv:
    """The daemon's commissioning environment (`unavailable` if it has none)."""
    env = getattr(ctx, "commissioning", None)
    if not isinstance(env, CommissioningEnv):
        raise OpError("unavailable", "this daemon has no commissioning support configured")
    return env


def vector3(args: Mapping[str, Any], key: str) -> np.ndarray:
    """A finite [x, y, z] argument in mm."""
    v = args.get(key)
    ok = isinstance(v, list | tuple) and len(v) == 3
    if not ok or not all(_finite(x) and abs(x) < MAX_ABS_MM for x in v):  # type: ignore[union-attr]
        raise OpError("bad_args", f"{key} = {v!r}: expected [x, y, z] in mm, finite")
    return np.array(v, dtype=np.float64)


def stations(args: Mapping[str, Any], ctx: OpContext) -> list[float]:
    """`stations_mm`: arc lengths to view from (default: where the trolley is now)."""
    v = args.get("stations_mm")
    if v is None:
        pos = ctx.controller.snapshot().get("position_mm") if ctx.controller else None
        if pos is None:
            raise OpError("bad_args", "stations_mm missing and the trolley position is unknown")
        return [float(pos)]
    if not isinstance(v, list) or not 1 <= len(v) <= MAX_STATIONS or not all(_finite(x) for x in v):
        raise OpError(
            "bad_args", f"stations_mm = {v!r}: expected 1-{MAX_STATIONS} finite arc lengths"
        )
    return [float(x) for x in v]


def board_spec(args: Mapping[str, Any]) -> BoardSpec:
    """`board`: the printed board's dimensions (default: BoardSpec())."""
    v = args.get("board")
    if v is None:
        return BoardSpec()
    if not isinstance(v, dict):
        raise OpError("bad_args", f"board = {v!r}: expected a map of BoardSpec fields")
    try:
        return BoardSpec.from_dict(v)
    except (TypeError, ValueError) as exc:
        raise OpError("bad_args", str(exc)) from exc


def image_targets(args: Mapping[str, Any]) -> tuple[tuple[float, float], ...]:
    """`image_targets`: where the board's centre goes in each station's views, as fractions of
    the image [[fx, fy], ...] (default: the centre and the four quarter points)."""
    v = args.get("image_targets")
    if v is None:
        return IMAGE_TARGETS
    why = f"image_targets = {v!r}: expected 1-{MAX_TARGETS} [fx, fy], each in (0, 1)"
    rows = number_rows(v, 2, 1, MAX_TARGETS, why)
    if not all(0.0 < x < 1.0 for row in rows for x in row):
        raise OpError("bad_args", why)
    return tuple((row[0], row[1]) for row in rows)


def number_rows(v: Any, width: int, least: int, most: int, why: str) -> list[tuple[float, ...]]:
    """A list of `least`-`most` rows of `width` finite numbers, as floats; OpError(why) if not."""
    if not isinstance(v, list) or not least <= len(v) <= most:
        raise OpError("bad_args", why)
    for row in v:
        if not isinstance(row, list | tuple) or len(row) != width:
            raise OpError("bad_args", why)
        if not all(_finite(x) for x in row):
            raise OpError("bad_args", why)
    return [tuple(float(x) for x in row) for row in v]


def thresholds(args: Mapping[str, Any]) -> intrinsics_run.Thresholds:
    """Optional `max_rms_px` and `min_views` overrides of the stated thresholds."""
    base = intrinsics_run.Thresholds()
    rms = args.get("max_rms_px", base.max_rms_px)
    views = args.get("min_views", base.min_views)
    if not _finite(rms) or not 0.0 < rms <= 5.0:
        raise OpError("bad_args", f"max_rms_px = {rms!r}: expected a number in (0, 5]")
    if isinstance(views, bool) or not isinstance(views, int) or not 3 <= views <= 500:
        raise OpError("bad_args", f"min_views = {views!r}: expected an integer in [3, 500]")
    return intrinsics_run.Thresholds(
        float(rms), views, base.max_rel_sigma_focal, base.max_sigma_centre_px
    )


async def op_calibrate_intrinsics(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start an intrinsics run: board_centre_mm (world, rough), stations_mm, board, write."""
    centre = vector3(args, "board_centre_mm")
    limits = thresholds(args)
    full = bool(args.get("full_distortion", False))

    def finish(
        views: list[Any], rig: Any, camera: Any
    ) -> tuple[dict[str, Any], Page, dict[str, Any]]:
        out = intrinsics_run.judge(views, camera, limits, full)
        updates = intrinsics_run.rig_update(out) if out.passed else {}
        summary = out.summary()
        if "head.angle_noise" in updates:  # measured at the views' rests
            noise = updates["head.angle_noise"]
            summary["head_noise_rad"] = noise.sigma
            summary["reasons"] = [*summary["reasons"], f"head read noise {noise.sigma:.2g} rad "
                                  f"({noise.provenance.note})"]  # fmt: skip
        return summary, intrinsics_run.page(out, limits), updates

    return _start_capture_run(ctx, args, "intrinsics", centre, finish)


def board_pose(args: Mapping[str, Any]) -> tuple[FloatArray, FloatArray]:
    """`board_pose` (4×4, world, surveyed) and its 6×6 local covariance from the σ given."""
    v = args.get("board_pose")
    try:
        T = np.array(v, dtype=np.float64)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.isfinite(T).all() or not np.allclose(T[3], [0, 0, 0, 1]):
        raise OpError("bad_args", f"board_pose = {v!r}: expected a 4×4 rigid transform (mm)")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise OpError("bad_args", "board_pose: its 3×3 block is not a rotation")
    sig_mm = args.get("board_sigma_mm", 1.0)
    sig_rad = args.get("board_sigma_rad", 1e-3)
    if not _finite(sig_mm) or not _finite(sig_rad) or sig_mm < 0 or sig_rad < 0:
        raise OpError("bad_args", "board_sigma_mm, board_sigma_rad: expected non-negative numbers")
    cov = np.diag([sig_rad**2] * 3 + [sig_mm**2] * 3)
    return T, cov


def _start_capture_run(
    ctx: OpContext, args: Mapping[str, Any], kind: str, centre: FloatArray,
    finish: Any,
) -> dict[str, Any]:  # fmt: skip
    """Start a run that captures board views along a plan, then calls `finish` on them.

    With `reuse_views`, the views the last board run filmed are solved again instead, when that
    run filmed the same board around the same centre from the same stations with the same zero
    (the head calibration from the intrinsics run's views: one filming for both solves).
    """
    env = env_of(ctx)
    spec = board_spec(args)
    where = stations(args, ctx)
    speed = float(args.get("speed_mm_s", TRAVEL_SPEED_MM_S))
    if not _finite(speed) or not 1.0 <= speed <= MAX_SPEED_MM_S:
        raise OpError(
            "bad_args", f"speed_mm_s = {args.get('speed_mm_s')!r}: expected 1-{MAX_SPEED_MM_S}"
        )
    reuse = args.get("reuse_views", False)
    if not isinstance(reuse, bool):
        raise OpError("bad_args", f"reuse_views = {reuse!r}: expected true or false")
    targets = image_targets(args)
    controller = _filming(ctx, env)
    head_limits = (ctx.pan_limits_rad, ctx.tilt_limits_rad)

    async def run(progress: Progress) -> dict[str, Any]:
        tap, rig, camera = _camera_now(env)
        filmed = _reusable(env, spec, centre, where) if reuse else None
        if filmed is not None:
            progress.update(phase=f"solving the views of {filmed.kind} run {filmed.job}")
            views = [dataclasses.replace(v) for v in filmed.views]  # a solve may mark outliers
            progress["planned"] = len(views)
        else:
            order = sweep(where, _trolley_s(controller, env))
            plan = board_plan(rig, camera, centre, order, targets, head_limits)
            progress["planned"] = len(plan)
            if not plan:
                raise AbortedError("no view of the board can be planned from these stations")
            io = RigIO(controller, tap, speed, home_s_mm=env.home_s_mm())
            views = await intrinsics_run.capture(io, plan, BoardDetector(spec), camera, progress)
            env.jobs.filmed = Filmed(
                _job_id(env), kind, spec.to_dict(), tuple(float(c) for c in centre),
                tuple(sorted(where)), io.home_s_mm, tuple(views),
            )  # fmt: skip
        progress["phase"] = "solving"
        summary, page, updates = await asyncio.to_thread(finish, views, rig, camera)
        summary["views_from"] = "filmed" if filmed is None else f"{filmed.kind} run {filmed.job}"
        return await _conclude(env, args, progress, kind, summary, page, updates)

    return _start(env, kind, run)


def _reusable(
    env: CommissioningEnv, spec: BoardSpec, centre: FloatArray, where: list[float]
) -> Filmed | None:
    """The last board filming, if it saw this board from these stations with today's zero."""
    filmed = env.jobs.filmed
    if filmed is None or filmed.board != spec.to_dict():
        return None
    same_stations = len(filmed.stations_mm) == len(where) and all(
        abs(a - b) <= REUSE_TOL_MM for a, b in zip(filmed.stations_mm, sorted(where), strict=True)
    )
    near = float(np.linalg.norm(np.subtract(filmed.centre_mm, centre))) <= REUSE_CENTRE_MM
    same_zero = abs(filmed.home_s_mm - env.home_s_mm()) <= REUSE_TOL_MM
    return filmed if same_stations and near and same_zero else None


def _trolley_s(controller: Any, env: CommissioningEnv) -> float | None:
    """The trolley's arc length now (None if the controller does not know it)."""
    pos = controller.snapshot().get("position_mm")
    return None if pos is None else float(pos) + env.home_s_mm()


def _clock_sigma_ms(controller: Any) -> float | None:
    """The link's clock-sync σ now (ms), as its estimator measures it; None before a fit.

    It grows with the link's load (slow round trips weigh less in its fit) and holds the
    link's asymmetry σ (host.service.wiring.CLOCK_ASYMMETRY_SIGMA_US); the rig file's value, a
    default until measured, does neither.
    """
    clock = getattr(getattr(controller, "session", None), "clock", None)
    if clock is None or not clock.ready:
        return None
    return float(clock.uncertainty_ns()) / 1e6


def _head_now(controller: Any) -> tuple[float, float] | None:
    """The head's (pan, tilt) now, where a plan's first view turns it from (None if unknown)."""
    head = controller.snapshot().get("head_rad")
    return None if not head else (float(head[0]), float(head[1]))


def _job_id(env: CommissioningEnv) -> int:
    """The id of the run in progress (the caller's own)."""
    job = env.jobs.current
    return -1 if job is None else job.id


async def op_calibrate_head(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start a head run: board_pose (surveyed), stations_mm; solves M_cr and T_w_track."""
    T_w_b, cov_b = board_pose(args)
    spec = board_spec(args)
    limits = head_run.HeadThresholds()

    def finish(
        views: list[Any], rig: Any, camera: Any
    ) -> tuple[dict[str, Any], Page, dict[str, Any]]:
        env = env_of(ctx)
        spec = env.spec()
        home_sigma = float(spec.track.home.sigma)  # the views' arc lengths carry it
        head_sigma = float(spec.head.angle_noise.sigma)  # ... and the head's read noise
        out = head_run.judge_head(
            views, rig, camera, T_w_b, cov_b, limits, env.camera_cov(), home_sigma, head_sigma
        )
        updates = head_run.head_rig_update(out, True, home_sigma) if out.passed else {}
        return out.summary(), head_run.head_page(out, limits), updates

    return _start_capture_run(
        ctx, args, "head", (T_w_b @ np.append(spec.centre_mm, 1.0))[:3], finish
    )


async def op_calibrate_check(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start the acceptance test: predicted against measured corners from new poses."""
    T_w_b, cov_b = board_pose(args)
    spec = board_spec(args)
    env = env_of(ctx)
    limit = args.get("max_rms_px", 1.0)
    if not _finite(limit) or not 0.0 < limit <= 10.0:
        raise OpError("bad_args", f"max_rms_px = {limit!r}: expected a number in (0, 10]")

    def finish(
        views: list[Any], rig: Any, camera: Any
    ) -> tuple[dict[str, Any], Page, dict[str, Any]]:
        out = head_run.check_views(views, rig, camera, T_w_b, float(limit))
        budget = env.budget()
        if budget is not None:
            out = head_run.with_prediction(out, budget[0], T_w_b, cov_b)
        return out.summary(), head_run.check_page(out, float(limit)), {}

    return _start_capture_run(
        ctx, args, "check", (T_w_b @ np.append(spec.centre_mm, 1.0))[:3], finish
    )


async def op_calibrate_latency(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start a latency run: board_pose, station_mm, span_mm, speed_mm_s, passes, write."""
    env = env_of(ctx)
    T_w_b, _ = board_pose(args)
    spec = board_spec(args)
    station = number(args, "station_mm", -MAX_ABS_MM, MAX_ABS_MM)
    span = number({"span_mm": 200.0, **args}, "span_mm", 20.0, 5000.0)
    speed = number({"speed_mm_s": 300.0, **args}, "speed_mm_s", 10.0, MAX_SPEED_MM_S)
    passes = count(args, "passes", 6, 2, 40)
    if ctx.controller is None or not ctx.controller.connected:
        raise OpError("unavailable", "the controller link is not up")
    if env.frames() is None or env.pose_at is None:
        raise OpError("unavailable", "no camera frames or no pose source in this daemon")
    controller, pose_at = ctx.controller, env.pose_at
    limits = latency_run.LatencyThresholds()
    centre = (T_w_b @ np.append(spec.centre_mm, 1.0))[:3]
    head_limits = (ctx.pan_limits_rad, ctx.tilt_limits_rad)

    async def run(progress: Progress) -> dict[str, Any]:
        tap, rig, camera = _camera_now(env)
        size = np.array([camera.width - 1.0, camera.height - 1.0])
        head = _head_now(controller)
        angles = aim_within(rig, camera, station, centre, size / 2, head_limits, head)
        if angles is None:
            raise AbortedError(f"the board cannot be aimed at from s = {station:.0f} mm")
        view = ViewTarget(station, angles[0], angles[1], f"s={station:.0f}")
        # to the span's start at the travel speed; only the passes go at `speed`
        io = RigIO(controller, tap, home_s_mm=env.home_s_mm())
        det = BoardDetector(spec)
        frames = await latency_run.capture_passes(
            io, tap, pose_at, det, view, span, speed, passes, progress
        )
        progress["phase"] = "solving"
        # the link's clock-sync error is common to every frame: its σ as the estimator
        # measures it during the passes (it grows with the link's load), never below the rig's
        clock_ms = max(env.spec().camera.clock_sync.sigma, _clock_sigma_ms(controller) or 0.0)
        out = await asyncio.to_thread(
            latency_run.judge, frames, rig, camera, T_w_b, env.latency_ms(), limits, clock_ms
        )
        updates = latency_run.latency_update(out) if out.passed else None
        page = latency_run.latency_page(out, limits)
        return await _conclude(env, args, progress, "latency", out.summary(), page, updates)

    return _start(env, "latency", run)


def aims(args: Mapping[str, Any]) -> list[ViewTarget]:
    """`aims`: [[s_mm, pan_rad, tilt_rad], ...], one per feature point (3-64)."""
    v = args.get("aims")
    why = f"aims = {v!r}: expected 3-{MAX_STATIONS} [s_mm, pan_rad, tilt_rad]"
    rows = number_rows(v, 3, 3, MAX_STATIONS, why)
    return [ViewTarget(s, pan, tilt, f"P{i + 1}") for i, (s, pan, tilt) in enumerate(rows)]


async def op_survey_workpiece(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start a workpiece survey: aims, optional model_points_mm, samples, noise_mm, write;
    or with method "camera": model_points_mm (the targets' model coordinates), stations_mm."""
    env = env_of(ctx)
    method = args.get("method", "rangefinder")
    if method == "camera":
        return _survey_workpiece_camera(ctx, args, env)
    if method != "rangefinder":
        raise OpError("bad_args", f"method = {method!r}: expected 'rangefinder' or 'camera'")
    targets = aims(args)
    model = args.get("model_points_mm")
    model_p = None
    if model is not None:
        model_p = np.array(model, dtype=np.float64) if isinstance(model, list) else np.zeros(0)
        if model_p.shape != (len(targets), 3) or not np.isfinite(model_p).all():
            raise OpError("bad_args", f"model_points_mm: expected {len(targets)} finite [x, y, z]")
    samples = count(args, "samples", 10, 1, 200)
    noise = number({"noise_mm": 1.0, **args}, "noise_mm", 0.0, 100.0)
    # where the calibrated rig puts the beam's origin (home and track surveys, ~1 mm)
    rig_sigma = number({"rig_sigma_mm": 1.0, **args}, "rig_sigma_mm", 0.0, 100.0)
    if ctx.controller is None or not ctx.controller.connected:
        raise OpError("unavailable", "the controller link is not up")
    tap = env.ranges() if env.ranges is not None else None
    if tap is None:
        raise OpError("unavailable", "no rangefinder readings (the rig file lists no surfaces?)")
    controller = ctx.controller

    async def run(progress: Progress) -> dict[str, Any]:
        rig, _ = env.kinematics()
        points = await survey_run.measure(_survey_io(env, controller), tap, rig, targets,
                                          samples, progress)  # fmt: skip
        sigma = float(np.hypot(survey_run.point_sigma_mm(noise, samples), rig_sigma))
        ok, reasons, fit = survey_run.judge(points, model_p, sigma)
        result = survey_run.summary(ok, reasons, points, fit)
        updates = survey_run.workpiece_update(fit, len(points)) if ok and fit else None
        page = survey_run.page(result)
        return await _conclude(env, args, progress, "workpiece", result, page, updates)

    return _start(env, "workpiece", run)


def _survey_workpiece_camera(
    ctx: OpContext, args: Mapping[str, Any], env: CommissioningEnv
) -> dict[str, Any]:
    """Start the camera survey: targets on the model's points, seen from several stations."""
    model = args.get("model_points_mm")
    model_p = np.array(model, dtype=np.float64) if isinstance(model, list) else np.zeros(0)
    if model_p.ndim != 2 or model_p.shape[1:] != (3,) or not 3 <= len(model_p) <= MAX_STATIONS:
        raise OpError("bad_args", "model_points_mm: expected 3-64 finite [x, y, z] (mm)")
    if not np.isfinite(model_p).all():
        raise OpError("bad_args", "model_points_mm: expected 3-64 finite [x, y, z] (mm)")
    where = stations(args, ctx)
    controller = _filming(ctx, env)
    head_limits = (ctx.pan_limits_rad, ctx.tilt_limits_rad)

    async def run(progress: Progress) -> dict[str, Any]:
        tap, rig, camera = _camera_now(env)
        spec = env.spec()
        rough = spec.workpiece.frame.matrix  # the drawing's: only to predict where to look
        points_w = transform_points(rough, model_p)
        order = sweep(where, _trolley_s(controller, env))
        head = _head_now(controller)
        views = targets_run.plan_views(rig, camera, points_w, order, head_limits, head)
        progress["planned"] = len(views)
        if not views:
            raise AbortedError("no view of the targets can be planned from these stations")
        io = RigIO(controller, tap, home_s_mm=env.home_s_mm())
        views = await targets_run.capture(io, views, rig, camera, points_w, progress)
        progress["phase"] = "solving"
        out = await asyncio.to_thread(targets_run.judge, views, rig, camera, model_p, spec)
        updates = targets_run.workpiece_update(out, spec) if out.passed else None
        page = targets_run.page(out)
        return await _conclude(env, args, progress, "workpiece", out.summary(), page, updates)

    return _start(env, "workpiece", run)


async def op_survey_home(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start a home survey: pan_rad, tilt_rad aiming the beam at an end wall; samples."""
    env = env_of(ctx)
    pan = number(args, "pan_rad", *ctx.pan_limits_rad)
    tilt = number(args, "tilt_rad", *ctx.tilt_limits_rad)
    samples = count(args, "samples", 20, 1, 500)
    noise = number({"noise_mm": 1.0, **args}, "noise_mm", 0.0, 100.0)
    wall = number({"wall_sigma_mm": 1.0, **args}, "wall_sigma_mm", 0.0, 100.0)
    # how far the rig file may put the beam's origin along the beam (the client's to give)
    rig_sigma = number({"rig_sigma_mm": 0.0, **args}, "rig_sigma_mm", 0.0, 100.0)
    max_sigma = number({"max_sigma_mm": home_run.MAX_SIGMA_MM, **args}, "max_sigma_mm", 0.01, 100.0)
    if ctx.controller is None or not ctx.controller.connected:
        raise OpError("unavailable", "the controller link is not up")
    tap = env.ranges() if env.ranges is not None else None
    scene = env.scene()
    if tap is None or scene is None:
        raise OpError(
            "unavailable", "no rangefinder readings or no surveyed surfaces in the rig file"
        )
    controller = ctx.controller

    async def run(progress: Progress) -> dict[str, Any]:
        rig, _ = env.kinematics()
        result = await home_run.survey_home(
            _survey_io(env, controller), tap, rig, scene, pan, tilt, samples, noise, wall,
            progress,
        )  # fmt: skip
        result = with_rig_sigma(result, rig_sigma, max_sigma)
        updates = home_run.home_update(result, samples) if result["passed"] else None
        page = home_run.home_page(result)
        return await _conclude(env, args, progress, "home", result, page, updates)

    return _start(env, "home", run)


def _filming(ctx: OpContext, env: CommissioningEnv) -> Any:
    """The controller for a run that needs camera frames (`unavailable` without either)."""
    if ctx.controller is None or not ctx.controller.connected:
        raise OpError("unavailable", "the controller link is not up")
    if env.frames() is None:
        raise OpError("unavailable", "no camera frames: the daemon has no camera source")
    return ctx.controller


def _camera_now(env: CommissioningEnv) -> tuple[FrameTap, Rig, CameraModel]:
    """A filming run's start: the camera's frames (aborts if it went away) and the rig now."""
    tap = env.frames()
    if tap is None:
        raise AbortedError("the camera went away")
    rig, camera = env.kinematics()
    return tap, rig, camera


def _ranging(ctx: OpContext, env: CommissioningEnv) -> tuple[Any, Any]:
    """The controller and its rangefinder tap (`unavailable` without either or a hall)."""
    if ctx.controller is None or not ctx.controller.connected:
        raise OpError("unavailable", "the controller link is not up")
    tap = env.ranges() if env.ranges is not None else None
    if tap is None or env.scene() is None:
        raise OpError(
            "unavailable", "no rangefinder readings or no surveyed surfaces in the rig file"
        )
    return ctx.controller, tap


async def op_survey_marks(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start a marks survey: samples, cross_speed_mm_s, aim_rad ([pan, tilt]), max_sigma_mm,
    marks (indices of the listed marks to survey; default all)."""
    env = env_of(ctx)
    samples = count(args, "samples", 20, 1, 500)
    cross = number({"cross_speed_mm_s": marks_run.CROSS_SPEED_MM_S, **args},
                   "cross_speed_mm_s", 5.0, MAX_SPEED_MM_S)  # fmt: skip
    limit = number({"max_sigma_mm": 2.0, **args}, "max_sigma_mm", 0.01, 50.0)
    aim = args.get("aim_rad")
    if aim is not None:
        if not isinstance(aim, list | tuple) or len(aim) != 2 or not all(_finite(a) for a in aim):
            raise OpError("bad_args", f"aim_rad = {aim!r}: expected [pan_rad, tilt_rad]")
        aim = (float(aim[0]), float(aim[1]))
    only = args.get("marks")
    if only is not None and (
        not isinstance(only, list) or not only
        or not all(isinstance(k, int) and not isinstance(k, bool) and k >= 0 for k in only)
    ):  # fmt: skip
        raise OpError("bad_args", f"marks = {only!r}: expected indices into track.marks")
    controller, tap = _ranging(ctx, env)
    head_limits = (ctx.pan_limits_rad, ctx.tilt_limits_rad)
    limits = marks_run.MarkThresholds(limit)

    async def run(progress: Progress) -> dict[str, Any]:
        spec = env.spec()
        result, marks = await marks_run.survey_marks(
            _survey_io(env, controller), tap, spec, *head_limits, samples, cross, aim, limits,
            progress, only,
        )  # fmt: skip
        listed = spec.track.marks
        updates = marks_run.marks_update(marks, samples, listed) if result["passed"] else None
        page = marks_run.marks_page(result, limits)
        return await _conclude(env, args, progress, "marks", result, page, updates)

    return _start(env, "marks", run)


def poses_arg(args: Mapping[str, Any]) -> list[ViewTarget] | None:
    """`aims`: an explicit pose list [[s_mm, pan_rad, tilt_rad], ...] (None: plan one)."""
    v = args.get("aims")
    if v is None:
        return None
    rows = number_rows(
        v, 3, 1, MAX_POSES, f"aims: expected 1-{MAX_POSES} [s_mm, pan_rad, tilt_rad]"
    )
    return [ViewTarget(s, pan, tilt, f"s={s:.0f}") for s, pan, tilt in rows]


async def op_calibrate_rangefinder(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start a mount calibration: stations_mm, pans, tilts_rad or aims; samples, speed_mm_s."""
    env = env_of(ctx)
    explicit = poses_arg(args)
    where = None if args.get("stations_mm") is None else stations(args, ctx)
    pans = count(args, "pans", rangefinder_run.DEFAULT_PANS, 3, 72)
    tilts = args.get("tilts_rad")
    if tilts is not None and (
        not isinstance(tilts, list) or not 1 <= len(tilts) <= 12
        or not all(_finite(t) and ctx.tilt_limits_rad[0] <= t <= ctx.tilt_limits_rad[1]
                   for t in tilts)
    ):  # fmt: skip
        raise OpError("bad_args", f"tilts_rad = {tilts!r}: expected 1-12 tilts within the limits")
    samples = count(args, "samples", 5, 1, 100)
    speed = number({"speed_mm_s": TRAVEL_SPEED_MM_S, **args}, "speed_mm_s", 1.0, MAX_SPEED_MM_S)
    base = rangefinder_run.MountThresholds()
    limits = rangefinder_run.MountThresholds(
        number({"max_rms_mm": base.max_rms_mm, **args}, "max_rms_mm", 0.01, 100.0)
    )
    controller, tap = _ranging(ctx, env)
    tilt_limits = ctx.tilt_limits_rad

    async def run(progress: Progress) -> dict[str, Any]:
        spec = env.spec()
        plan = explicit or rangefinder_run.default_plan(
            spec, where, pans, None if tilts is None else [float(t) for t in tilts], tilt_limits
        )
        progress["planned"] = len(plan)
        if not plan:
            raise AbortedError("no pose of the plan puts the beam cleanly on a surveyed surface")
        io = _survey_io(env, controller, speed)
        samples_got, missed = await rangefinder_run.capture(io, tap, plan, samples, progress)
        progress["phase"] = "solving"
        fit = await asyncio.to_thread(rangefinder_run.fit_mount, spec, samples_got, limits)
        result = {**fit.summary(), "planned": len(plan), "no_reading": missed}
        updates = rangefinder_run.mount_update(fit) if fit.passed else None
        page = rangefinder_run.mount_page(fit, limits)
        return await _conclude(env, args, progress, "rangefinder", result, page, updates)

    return _start(env, "rangefinder", run)


async def op_survey_track(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start a track survey (the first corner's place, the arcs' radius): stations_mm, pans,
    samples, speed_mm_s, max_corner_sigma_mm, max_radius_sigma_mm, max_rms_mm."""
    env = env_of(ctx)
    where = None if args.get("stations_mm") is None else stations(args, ctx)
    pans = count(args, "pans", track_run.DEFAULT_PANS, 3, 72)
    samples = count(args, "samples", 5, 1, 100)
    speed = number({"speed_mm_s": TRAVEL_SPEED_MM_S, **args}, "speed_mm_s", 1.0, MAX_SPEED_MM_S)
    base = track_run.TrackThresholds()
    limits = track_run.TrackThresholds(
        number({"max_corner_sigma_mm": base.max_corner_sigma_mm, **args},
               "max_corner_sigma_mm", 0.01, 100.0),
        number({"max_radius_sigma_mm": base.max_radius_sigma_mm, **args},
               "max_radius_sigma_mm", 0.01, 100.0),
        number({"max_rms_mm": base.max_rms_mm, **args}, "max_rms_mm", 0.01, 100.0),
    )  # fmt: skip
    controller, tap = _ranging(ctx, env)
    tilt_limits = ctx.tilt_limits_rad

    async def run(progress: Progress) -> dict[str, Any]:
        spec = env.spec()
        views = track_run.plan(spec, where, pans, tilt_limits)
        if isinstance(views, str):
            raise AbortedError(views)
        progress["planned"] = len(views)
        io = _survey_io(env, controller, speed)
        fit, missed = await track_run.survey_track(io, tap, spec, views, samples, limits, progress)
        result = {**fit.summary(), "planned": len(views), "no_reading": missed}
        updates = track_run.track_update(spec, fit, samples) if fit.passed else None
        page = track_run.track_page(fit, limits)
        return await _conclude(env, args, progress, "track", result, page, updates)

    return _start(env, "track", run)


def with_rig_sigma(
    result: dict[str, Any], rig_sigma_mm: float, max_sigma_mm: float
) -> dict[str, Any]:
    """A home survey's σ with the beam origin's own (along the beam, over |∂range/∂s|), judged
    against `max_sigma_mm`: before the head is calibrated, that and not the reading sets it."""
    if "sigma_mm" not in result or not math.isfinite(result.get("slope", math.nan)):
        return result
    sigma = math.hypot(result["sigma_mm"], rig_sigma_mm / abs(result["slope"]))
    ok = sigma <= max_sigma_mm
    why = (
        f"home at s = {result['home_mm']:.2f} ± {sigma:.2f} mm (reading ± "
        f"{result['sigma_mm']:.2f} mm, the rig's beam origin ± {rig_sigma_mm:.2f} mm)"
        if ok
        else f"σ {sigma:.2f} mm > {max_sigma_mm} mm"
    )
    out = {**result, "passed": ok, "reasons": [why], "sigma_mm": sigma,
           "reading_sigma_mm": result["sigma_mm"], "rig_sigma_mm": rig_sigma_mm}  # fmt: skip
    return {**out, "table": home_run.home_table(out)} if "home_before_mm" in out else out


class _NoCamera:
    """The survey needs no frames: a source that never delivers one."""

    def read(self) -> None:
        return None

    def close(self) -> None:
        return None


def _write(root: Path, kind: str, page: Page) -> str:
    """A run's report directory and page."""
    return str(write_page(run_dir(root, kind), page))


async def _conclude(
    env: CommissioningEnv, args: Mapping[str, Any], progress: Progress, kind: str,
    result: Mapping[str, Any], page: Page, updates: Mapping[str, Any] | None,
) -> dict[str, Any]:  # fmt: skip
    """How every run ends: its report page, then the rig file updated only when the run passed,
    `write` allows it and the daemon has a rig file (the daemon rereads it after)."""
    report = await asyncio.to_thread(_write, env.report_root, kind, page)
    written = None
    if result["passed"] and updates and bool(args.get("write", True)) and env.rig_path:
        progress["phase"] = "writing"
        await asyncio.to_thread(update_rig, env.rig_path, updates, f"commissioning: {kind}")
        written = str(env.rig_path)
        if env.after_write is not None:
            await env.after_write()
    progress["phase"] = "done"
    return {**result, "report": report, "written": written, "rig_file": _path(env)}


def _start(env: CommissioningEnv, kind: str, run: Any) -> dict[str, Any]:
    """Start a run on the job board (`busy` while another runs); its id."""
    try:
        job = env.jobs.start(kind, run)
    except JobBusyError as exc:
        raise OpError("busy", str(exc)) from exc
    return {"job": job.id, "kind": job.kind}


def _survey_io(env: CommissioningEnv, controller: Any, speed: float = TRAVEL_SPEED_MM_S) -> RigIO:
    """Motion for a rangefinder run (it needs no frames)."""
    return RigIO(controller, env.frames() or FrameTap(_NoCamera()), speed,
                 home_s_mm=env.home_s_mm())  # fmt: skip


def count(args: Mapping[str, Any], key: str, default: int, lo: int, hi: int) -> int:
    """An integer argument in [lo, hi]."""
    v = args.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise OpError("bad_args", f"{key} = {v!r}: expected an integer in [{lo}, {hi}]")
    return v


async def op_commissioning_status(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """The current (or last) run: state, progress and, when over, its result."""
    env = env_of(ctx)
    job_id = args.get("job")
    if job_id is not None and (isinstance(job_id, bool) or not isinstance(job_id, int)):
        raise OpError("bad_args", f"job = {job_id!r}: expected a run id")
    job = env.jobs.get(job_id)
    if job is None:
        return {"state": "none"}
    return job.status()


async def op_commissioning_cancel(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Cancel the running run (nothing is written)."""
    return {"cancelled": env_of(ctx).jobs.cancel_all("cancelled by a client")}


def cancel_runs(ctx: OpContext, reason: str) -> None:
    """Hook for STOP and ESTOP: end any run before the stop is sent."""
    env = getattr(ctx, "commissioning", None)
    if isinstance(env, CommissioningEnv):
        env.jobs.cancel_all(reason)


def _path(env: CommissioningEnv) -> str | None:
    return None if env.rig_path is None else str(env.rig_path)


def _finite(x: Any) -> bool:
    return not isinstance(x, bool) and isinstance(x, int | float) and math.isfinite(x)


# op name → (handler, the least role that may run it); merged into host.control.ops.OPS
COMMISSIONING_OPS: dict[str, tuple[Handler, Role]] = {
    "calibrate_intrinsics": (op_calibrate_intrinsics, Role.OPERATOR),
    "calibrate_head": (op_calibrate_head, Role.OPERATOR),
    "calibrate_check": (op_calibrate_check, Role.OPERATOR),
    "calibrate_latency": (op_calibrate_latency, Role.OPERATOR),
    "survey_workpiece": (op_survey_workpiece, Role.OPERATOR),
    "survey_home": (op_survey_home, Role.OPERATOR),
    "survey_marks": (op_survey_marks, Role.OPERATOR),
    "calibrate_rangefinder": (op_calibrate_rangefinder, Role.OPERATOR),
    "survey_track": (op_survey_track, Role.OPERATOR),
    "commissioning_status": (op_commissioning_status, Role.VIEWER),
    "commissioning_cancel": (op_commissioning_cancel, Role.OPERATOR),
}
