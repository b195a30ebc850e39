"""The error budget against seeded commissioned rigs: predicted beside measured overlay σ.

Run: python benchmarks/bench_budget.py [--seeds N]   (prints `metric: value` lines, ~25 s a seed)

Each seed is a built rig (hil_sim.true_rig), commissioned offline with the real solvers on
rendered views as the demo does (tests/experiments/seeded_rigs.py: intrinsics, then head on the
same views with the board surveyed to 1 mm / 1 mrad, the rig file as those runs write it; the
head stands and reads as the simulator's plant does, and its read noise is measured at the
views' rests). At the demo's observation
points and two more around the loop, aimed at the model's centre, the measured overlay error is
drawn − true pixel of the model's visible vertices (the truth's side); across the rigs its RMS
is the measured σ, beside the RMS of the budget's predicted σ of each rig's own file, and their
ratio per pose. The ratio predicted / measured should be 1 (issue 11: within ±30 %); the
pooled ratio (all poses, so weighted to the largest errors) has a 68 % interval, a bootstrap
over the rigs: with few rigs the measured σ is itself uncertain (~1/√(2·rigs·dof)).

First, the joint covariance itself: the normalised error (NEES) of intrinsics, M_cr and
placement against the truth, with the joint block, with it dropped (block-diagonal), and
without the head angles' share in the hand-eye covariance (each view's share is the rest
median's σ, `head_noise.rest_sigma`, as `calibrate head` passes it).

Cases (the workpiece frame is what differs):
- `surveyed`: the workpiece surveyed independently (total station, 1 mm / 1 mrad);
- `rig_only`: the workpiece frame exact: the budget of the commissioned rig alone;
- `board_relative`: the workpiece surveyed in the board's frame, so the board survey's error is
  common to the workpiece and the track placement and cancels in part; the rig file has the
  cross terms (`with_block`); `..._no_cross` is the same rig file with them removed;
- `camera`: the workpiece surveyed as the demo does, by the camera through the commissioned rig
  (targets rendered through the true lens, triangulated, written with its dependence on the
  intrinsics, M_cr, placement and zero): most of the rig's error cancels near the survey;
- `camera_datasheet_head`: the same, with the datasheet's head noise in the rig file instead of
  the measured one (what the demo wrote before): the head reads far better than that at rest.
`--demo DIR ...` instead reads the commissioned demo's runs (`orbitar demo --tolerances on
--out DIR`, one per seed) and prints, per observation point and pooled, RMS over the runs of
the measured static offset beside that of the predicted σ: one run is one draw of its rig's
calibration error, so only the ratio over seeds says whether the budget's σ is right.
Last, `budget_ms_per_pose`: the budget's cost at one pose (the status op evaluates it off the
daemon's loop at every new pose).
Each case also prints the budget without the `[covariance]` cross terms (`_no_cross`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from host.demo.report_pages import budget_over_runs
from host.experiments.budget import inputs_from_rig, overlay_sigma
from host.geometry.model import manipulator_wireframe
from host.rig import Pose6
from host.rig.schema import HEAD_ANGLE_SIGMA_RAD
from tests.experiments.seeded_rigs import (
    Commissioned,
    board_relative_workpiece,
    camera_surveyed_workpiece,
    commission,
    joint_nees,
    observation_poses,
    predicted_and_measured,
    replace_workpiece,
)

OFFSETS_MM = (0.0, 300.0, 2000.0, 3000.0, 7000.0)  # the demo's three, then along the loop
BOOTSTRAP = 2000


def _ratio(meas: np.ndarray, pred: np.ndarray, rng: np.random.Generator) -> tuple[float, ...]:
    """sqrt(mean pred / mean meas) over the rigs (rows), with a bootstrap 68 % interval."""
    ok = np.isfinite(meas) & np.isfinite(pred)
    m = np.where(ok, meas, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    p = np.where(ok, pred, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    r = float(np.sqrt(p.mean() / m.mean()))
    idx = rng.integers(0, len(m), (BOOTSTRAP, len(m)))
    boot = np.sqrt(p[idx].mean(axis=1) / m[idx].mean(axis=1))
    lo, hi = np.percentile(boot, [16, 84])
    return r, float(lo), float(hi), float(np.sqrt(m.mean())), float(np.sqrt(p.mean()))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument(
        "--demo", nargs="+", metavar="DIR", default=None,
        help="instead: the commissioned demo's runs (results.json): predicted beside measured",
    )  # fmt: skip
    args = ap.parse_args()
    if args.demo:
        runs = [json.loads((Path(d) / "results.json").read_text()) for d in args.demo]
        print("\n".join(budget_over_runs(runs)))
        return
    points = manipulator_wireframe().vertices
    t0 = time.perf_counter()
    base = [commission(seed) for seed in range(1, args.seeds + 1)]
    print(f"rigs: {len(base)}")
    print(f"commission_s_per_rig: {(time.perf_counter() - t0) / len(base):.1f}")
    for block_diagonal in (False, True):
        values = [joint_nees(c, block_diagonal) for c in base]
        tag = "block_diagonal" if block_diagonal else "joint"
        print(
            f"nees_{tag}_mean: {np.mean([v for v, _ in values]):.1f} "
            f"(dof {values[0][1]}; median {np.median([v for v, _ in values]):.1f})"
        )
    # the same views without the head angles' share in the hand-eye covariance: on the first
    # four seeds
    plain = [joint_nees(commission(seed, head_noise_modelled=False)) for seed in range(1, 5)]
    print(f"nees_joint_without_head_share_mean: {np.mean([v for v, _ in plain]):.1f} (4 rigs)")
    cases = {
        "surveyed": base,
        "rig_only": [replace_workpiece(c, Pose6(c.truth.workpiece.frame.matrix)) for c in base],
        "board_relative": [
            board_relative_workpiece(c, np.random.default_rng([c.seed, 11])) for c in base
        ],
        "camera": _surveyed_by_camera(base),
        "camera_datasheet_head": _surveyed_by_camera(
            [commission(c.seed, measure_head=False) for c in base]
        ),
    }
    noise = [c.host.head.angle_noise.sigma for c in base]
    print(
        f"head_noise_measured_rad: {np.mean(noise):.2e} (range {min(noise):.1e}-"
        f"{max(noise):.1e}; datasheet {HEAD_ANGLE_SIGMA_RAD:.2e})"
    )
    rng = np.random.default_rng(0)
    for name, rigs in cases.items():
        for strip in (False, True):
            tag = f"{name}{'_no_cross' if strip else ''}"
            meas, pred = predicted_and_measured(rigs, OFFSETS_MM, points, strip)
            for j, off in enumerate(OFFSETS_MM):
                col_m, col_p = meas[:, j], pred[:, j]
                ok = np.isfinite(col_m)
                if not ok.any():
                    continue
                p, m = np.sqrt(col_p[ok].mean()), np.sqrt(col_m[ok].mean())
                print(
                    f"{tag}_at_{off:.0f}mm_predicted_px: {p:.3f}  measured_px: {m:.3f}  "
                    f"ratio: {p / m:.3f}"
                )
            r, lo, hi, m, p = _ratio(meas, pred, rng)
            print(f"{tag}_predicted_px: {p:.3f}  measured_px: {m:.3f}  (all poses pooled)")
            print(f"{tag}_ratio_predicted_over_measured: {r:.3f} (68 % {lo:.2f}-{hi:.2f})")
    _timing(cases["camera"][0], points)


def _surveyed_by_camera(rigs: list[Commissioned]) -> list[Commissioned]:
    """The camera survey on each rig; one that fails (as it would fail the demo's
    commissioning) is named and left out."""
    out = []
    for c in rigs:
        try:
            out.append(camera_surveyed_workpiece(c))
        except RuntimeError as exc:
            print(f"camera_survey_failed: {exc}")
    return out


def _timing(c: Commissioned, points: np.ndarray, repeats: int = 20) -> None:
    """The budget's cost at one pose, as the status op pays it (in a worker thread)."""
    inputs = inputs_from_rig(c.host)
    pose = observation_poses(c, (0.0,), points.mean(axis=0))[0]
    t0 = time.perf_counter()
    for _ in range(repeats):
        overlay_sigma(inputs, *pose, points)
    print(f"budget_ms_per_pose: {(time.perf_counter() - t0) / repeats * 1e3:.1f}")


if __name__ == "__main__":
    main()
