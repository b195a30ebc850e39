"""Commissioning accuracy and cost: intrinsics with skew on seeded true lenses, and the budget.

Run: python benchmarks/bench_commissioning.py   (prints `metric: value` lines, ~1 min)

Intrinsics: for each seed a lens off Table 1 by manufacturing tolerances renders 20 ChArUco
views (synthetic camera: true lens, pixel noise); our solve (skew refined, σ from the
Jacobian) runs beside OpenCV's skew-free calibrateCamera on the same corners. Printed: the
worst |error| / reported σ over all parameters and seeds (≤ 3 is honest), the skew's error,
both RMS and both times. Budget: the first-order overlay σ beside a Monte Carlo of the same
inputs, and their times.
"""

from __future__ import annotations

import dataclasses
import time

import cv2
import numpy as np

from hil_sim.camera import SyntheticCamera
from host.calibration.board import BoardDetector, BoardSpec
from host.calibration.intrinsics import BASE_KEYS, calibrate_with_rejection
from host.experiments.budget import BudgetInputs, monte_carlo, overlay_sigma
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import euler_zyx, make_T

SEEDS = (1, 2, 3, 4, 5)
VIEWS = 20
SPEC = BoardSpec()


def true_lens(rng: np.random.Generator) -> CameraModel:
    """Table 1 off by tolerances: 1 % focal length, 5 px centre, 0.3 px skew, k1/k2."""
    b = CameraModel()
    return dataclasses.replace(
        b, fx=b.fx * (1 + rng.normal(0, 0.01)), fy=b.fy * (1 + rng.normal(0, 0.01)),
        u0=b.u0 + rng.normal(0, 5), v0=b.v0 + rng.normal(0, 5), skew=b.skew + rng.normal(0, 0.3),
        k1=b.k1 + rng.normal(0, 0.1), k2=b.k2 + rng.normal(0, 0.3),
    )  # fmt: skip


def views(
    truth: CameraModel, rng: np.random.Generator
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Detected corners of VIEWS rendered boards."""
    det, sim = BoardDetector(SPEC), SyntheticCamera(truth, seed=int(rng.integers(1 << 30)))
    obj, img = [], []
    for _ in range(VIEWS):
        R = euler_zyx(*rng.uniform([-0.3, -0.6, -0.6], [0.3, 0.6, 0.6]))
        c = np.array([rng.uniform(-250, 250), rng.uniform(-200, 200), rng.uniform(2600, 4000)])
        found = det.detect(sim.render_board(make_T(R, c - R @ SPEC.centre_mm), det.board).image)
        if found is not None:
            obj.append(found.object_points)
            img.append(found.image_points)
    return obj, img


def intrinsics() -> None:
    """Our solve beside OpenCV's on the same corners, over the seeds."""
    worst, skew_err, ours_rms, cv_rms, t_ours, t_cv = 0.0, [], [], [], [], []
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        truth = true_lens(rng)
        obj, img = views(truth, rng)
        t0 = time.perf_counter()
        res = calibrate_with_rejection(obj, img, truth.size)
        t_ours.append(time.perf_counter() - t0)
        o32 = [o.astype(np.float32) for o in obj]
        i32 = [i.astype(np.float32) for i in img]
        t0 = time.perf_counter()
        flags = cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
        rms, *_ = cv2.calibrateCamera(o32, i32, truth.size, np.eye(3), np.zeros(5), flags=flags)
        t_cv.append(time.perf_counter() - t0)
        worst = max(
            worst,
            *(abs(getattr(res.camera, k) - getattr(truth, k)) / res.std[k] for k in BASE_KEYS),
        )
        skew_err.append(abs(res.camera.skew - truth.skew))
        ours_rms.append(res.rms_px)
        cv_rms.append(float(rms))
    print(f"intrinsics_seeds: {len(SEEDS)}")
    print(f"intrinsics_worst_error_over_sigma: {worst:.2f}")
    print(f"intrinsics_skew_error_px_max: {max(skew_err):.3f}")
    print(f"intrinsics_rms_px_ours: {np.mean(ours_rms):.4f}")
    print(f"intrinsics_rms_px_opencv_no_skew: {np.mean(cv_rms):.4f}")
    print(f"intrinsics_solve_s_ours: {np.median(t_ours):.3f}")
    print(f"intrinsics_solve_s_opencv: {np.median(t_cv):.3f}")


def budget() -> None:
    """First order beside Monte Carlo at two poses."""
    cam_sig = np.array([2.0, 2.0, 0.2, 0.3, 0.3, 0.005, 0.13, 0.0, 0.0, 0.0])
    pose = np.diag([3e-4**2] * 3 + [1.0] * 3)
    T_w_p = make_T(np.eye(3), [-300.0, -300.0, 0.0])
    inp = BudgetInputs(Rig(), CameraModel(), T_w_p, np.diag(cam_sig**2), pose, pose, pose,
                       0.3, (2e-4, 2e-4), 1e-3, 100.0)  # fmt: skip
    pts = manipulator_wireframe().vertices
    for s in (500.0, 2000.0):
        pan, tilt = Rig().aim(s, [-300.0, -300.0, 300.0])
        t0 = time.perf_counter()
        first = overlay_sigma(inp, s, pan, tilt, pts)
        t1 = time.perf_counter()
        mc = monte_carlo(inp, s, pan, tilt, pts, n=2000, seed=1)
        t2 = time.perf_counter()
        print(f"budget_s{s:.0f}_first_order_px: {first.sigma_px:.3f}")
        print(f"budget_s{s:.0f}_monte_carlo_px: {mc:.3f}")
        print(f"budget_s{s:.0f}_first_order_ms: {(t1 - t0) * 1e3:.1f}")
        print(f"budget_s{s:.0f}_monte_carlo_2000_ms: {(t2 - t1) * 1e3:.1f}")


if __name__ == "__main__":
    intrinsics()
    budget()
