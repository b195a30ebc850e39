"""`orbitar calibrate latency`: the offset between a frame's stamp and its exposure.

The head holds the surveyed board in view while the trolley passes back and forth at constant
speed. For every frame, the daemon's own pose source (`pose_at(stamp)`, the encoder and head
buffers with the latency now in the rig file) says where the trolley was; the board's corners
say where it really was: s* is the arc length that best reprojects them (Gauss-Newton in one
variable, head angles from the pose source). With a stamp late by δ the difference is
s(stamp) − s* = v·δ + b: a regression over both directions of travel separates δ (the slope
against the speed) from any static offset b (home, track placement), as render engines'
automatic delay detection does. The new latency is the old plus δ, with σ from the regression.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.calibration.board import BoardDetector, Detection
from host.commissioning.frames import FrameTap
from host.commissioning.motion import AbortedError, RigIO
from host.commissioning.plan import ViewTarget
from host.commissioning.report import Page, text_table
from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray
from host.rig import Provenance, Scalar

PoseAt = Callable[[int], tuple[float, float, float] | None]  # stamp → (s_mm, pan, tilt)
SPEED_TOL = 0.05  # frames within 5 % of the commanded speed are at constant speed
VELOCITY_WINDOW_NS = 20_000_000
POSE_WAIT_NS = 150_000_000  # the samples after a stamp have arrived by then (link latency)
GN_STEPS = 8
S_STEP_MM = 0.01
PASS_TIMEOUT_S = 30.0
POLL_S = 0.005


@dataclass(frozen=True)
class LatencyThresholds:
    """What a passing latency calibration must reach."""

    min_frames: int = 12
    max_sigma_ms: float = 2.0
    # A frame is stamped at or after its exposure (at delivery, or at a trigger): a latency
    # below this by more than 3 σ is not a camera's; the passes measured something else
    # (a jump of the pose source's arc length, a clock step).
    min_ms: float = 0.0

    def text(self) -> str:
        """One line for the verdict."""
        return (
            f"≥ {self.min_frames} frames at constant speed, σ ≤ {self.max_sigma_ms} ms, "
            f"latency ≥ {self.min_ms} ms within 3 σ"
        )


@dataclass(frozen=True)
class PassFrame:
    """One frame taken while passing: its stamp, the board's corners, and the pose source's view."""

    stamp_ns: int
    detection: Detection
    s_mm: float  # the pose source's arc length at the stamp
    pan_rad: float
    tilt_rad: float
    v_mm_s: float  # the pose source's speed at the stamp


@dataclass
class LatencyOutcome:
    """Verdict, the estimate and the regression's data."""

    passed: bool
    reasons: list[str]
    old_ms: float
    delta_ms: float = math.nan
    sigma_ms: float = math.nan
    bias_mm: float = math.nan
    frames: int = 0
    residual_mm: float = math.nan

    @property
    def new_ms(self) -> float:
        """The latency to write."""
        return self.old_ms + self.delta_ms

    def summary(self) -> dict[str, Any]:
        """Plain values."""
        rows: list[list[str | float]] = [
            ["latency before (ms)", round(self.old_ms, 3)],
            ["latency after (ms)", round(self.new_ms, 3)],
            ["σ (ms)", round(self.sigma_ms, 3)],
            ["static offset b (mm)", round(self.bias_mm, 3)],
            ["frames", self.frames],
        ]
        return {
            "passed": self.passed, "reasons": self.reasons, "latency_ms": self.new_ms,
            "sigma_ms": self.sigma_ms, "delta_ms": self.delta_ms, "bias_mm": self.bias_mm,
            "frames": self.frames, "residual_mm": self.residual_mm,
            "table": text_table(["quantity", "value"], rows),
        }  # fmt: skip


async def capture_passes(
    io: RigIO, tap: FrameTap, pose_at: PoseAt, detector: BoardDetector, view: ViewTarget,
    span_mm: float, speed_mm_s: float, passes: int, progress: dict[str, Any],
) -> list[PassFrame]:  # fmt: skip
    """Aim at the board from the middle, then pass back and forth from the end of the span
    nearer the trolley, keeping every frame.

    The pose source's view of each frame is taken during the pass, as soon as the samples after
    its stamp have arrived: its buffers reach back only the registration horizon (2 s), less
    than a few passes take.
    """
    now = io.s_mm(io.snapshot())
    first = -1.0 if now is not None and now > view.s_mm else 1.0  # the first pass's direction
    start = ViewTarget(view.s_mm - first * span_mm / 2, view.pan_rad, view.tilt_rad, view.label)
    await io.go(start)
    raw: list[tuple[Frame, tuple[float, float, float, float] | None]] = []
    for k in range(passes):
        progress.update(phase="passing", view=k + 1, of=passes)
        direction = first if k % 2 == 0 else -first
        target = view.s_mm + direction * span_mm / 2 - io.home_s_mm
        io.snapshot()
        await io.controller.move_to(target, speed_mm_s)
        raw += await _frames_until_still(io, tap, target, pose_at)
    progress["phase"] = "measuring"
    out = []
    for frame, got in raw:
        if got is None or abs(abs(got[3]) - speed_mm_s) > SPEED_TOL * speed_mm_s:
            continue
        det = await asyncio.to_thread(detector.detect, frame.image)
        if det is not None:
            out.append(PassFrame(frame.exposure_ns, det, *got))
    return out


async def _frames_until_still(
    io: RigIO, tap: FrameTap, target_mm: float, pose_at: PoseAt
) -> list[tuple[Frame, tuple[float, float, float, float] | None]]:
    """Every new frame until the trolley is back at rest at its target, with its pose."""
    frames: list[tuple[Frame, tuple[float, float, float, float] | None]] = []
    waiting: list[Frame] = []
    last = -1
    deadline = time.monotonic() + PASS_TIMEOUT_S
    await asyncio.sleep(0.05)  # let the move begin
    while True:
        frame = tap.latest()
        if frame is not None and frame.index != last:
            last = frame.index
            waiting.append(frame)
        now = time.monotonic_ns()
        while waiting and now > waiting[0].exposure_ns + POSE_WAIT_NS:
            f = waiting.pop(0)
            frames.append((f, _pose_and_speed(pose_at, f.exposure_ns)))
        snap = io.snapshot()
        pos = snap.get("position_mm")
        if snap.get("state") == "READY" and pos is not None and abs(float(pos) - target_mm) < 0.5:
            frames += [(f, _pose_and_speed(pose_at, f.exposure_ns)) for f in waiting]
            return frames
        if time.monotonic() > deadline:
            raise AbortedError(f"pass to {target_mm:.0f} mm not done within {PASS_TIMEOUT_S:.0f} s")
        await asyncio.sleep(POLL_S)


def _pose_and_speed(pose_at: PoseAt, t_ns: int) -> tuple[float, float, float, float] | None:
    """(s, pan, tilt, v) from the pose source at t_ns, v by a central difference."""
    now, a, b = (
        pose_at(t_ns),
        pose_at(t_ns - VELOCITY_WINDOW_NS),
        pose_at(t_ns + VELOCITY_WINDOW_NS),
    )
    if now is None or a is None or b is None:
        return None
    v = (b[0] - a[0]) / (2 * VELOCITY_WINDOW_NS / 1e9)
    return now[0], now[1], now[2], v


def board_arc_length(rig: Rig, camera: CameraModel, T_w_b: FloatArray, f: PassFrame) -> float:
    """The arc length whose camera pose best reprojects the frame's corners (head angles fixed)."""
    X, uv = f.detection.object_points, f.detection.image_points
    s = f.s_mm

    def res(s_mm: float) -> FloatArray:
        pred, _ = camera.project_world(rig.T_c_w(s_mm, f.pan_rad, f.tilt_rad) @ T_w_b, X)
        out: FloatArray = (pred - uv).ravel()
        return out

    for _ in range(GN_STEPS):
        r = res(s)
        J = (res(s + S_STEP_MM) - r) / S_STEP_MM
        step = -float(J @ r) / max(float(J @ J), 1e-12)
        s += step
        if abs(step) < 1e-4:
            break
    return s


def judge(
    frames: Sequence[PassFrame], rig: Rig, camera: CameraModel, T_w_b: FloatArray, old_ms: float,
    limits: LatencyThresholds, clock_sigma_ms: float = 0.0,
) -> LatencyOutcome:  # fmt: skip
    """Regress s(stamp) − s* on the speed: slope δ, intercept b.

    δ's σ is the regression's and `clock_sigma_ms` in quadrature: the pose source's samples
    reach the frames' clock through the link's clock sync, whose error at the time is common to
    every frame (the regression takes it for latency and its residuals cannot show it). The
    threshold applies to the regression's σ, the part more or faster passes reduce.
    """
    n = len(frames)
    speeds = [f.v_mm_s for f in frames]
    if n < limits.min_frames or not (min(speeds, default=0) < 0 < max(speeds, default=0)):
        why = (
            f"too few frames at constant speed in both directions: {n}, need ≥ {limits.min_frames}"
        )
        return LatencyOutcome(False, [why], old_ms, frames=n)
    d = np.array([f.s_mm - board_arc_length(rig, camera, T_w_b, f) for f in frames])
    A = np.column_stack([np.array(speeds) / 1e3, np.ones(n)])  # δ in ms, b in mm
    coef, *_ = np.linalg.lstsq(A, d, rcond=None)
    r = d - A @ coef
    var = float(r @ r) / max(n - 2, 1)
    cov = var * np.linalg.inv(A.T @ A)
    fit_sigma = float(np.sqrt(cov[0, 0]))
    delta, sigma = float(coef[0]), float(np.hypot(fit_sigma, clock_sigma_ms))
    out = LatencyOutcome(True, [], old_ms, delta, sigma, float(coef[1]), n, float(np.sqrt(var)))
    if fit_sigma > limits.max_sigma_ms:  # what the passes control; the clock's σ is written
        out.passed = False
        why = f"σ {fit_sigma:.2f} ms > {limits.max_sigma_ms} ms (more passes, or faster)"
        out.reasons = [why]
    elif out.new_ms + 3.0 * sigma < limits.min_ms:
        out.passed = False
        out.reasons = [
            f"latency {out.new_ms:.2f} ± {sigma:.2f} ms: a frame cannot be stamped before its "
            f"exposure (< {limits.min_ms} ms by more than 3 σ); the pose source's arc length "
            "or the link's clock jumped during the passes: run it again"
        ]
    else:
        out.reasons = [
            f"latency {out.new_ms:.2f} ± {sigma:.2f} ms over {n} frames (was {old_ms:.2f} ms)"
        ]
    return out


def latency_update(outcome: LatencyOutcome) -> dict[str, Any]:
    """`camera.latency` for the rig file."""
    if not outcome.passed:
        raise ValueError("only a passing calibration is written")
    prov = Provenance.now(
        "calibrate latency (passes past a board)", outcome.residual_mm, "mm", outcome.frames
    )
    return {"camera.latency": Scalar(outcome.new_ms, outcome.sigma_ms, prov)}


def latency_page(outcome: LatencyOutcome, limits: LatencyThresholds) -> Page:
    """The report page."""
    pg = Page(
        "Camera latency", outcome.passed, outcome.reasons, limits.text(), data=outcome.summary()
    )
    pg.preformatted.append(("Result", outcome.summary()["table"]))
    return pg
