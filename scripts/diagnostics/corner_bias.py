"""Diagnostic (scoring only, never a result): how far detected ChArUco corners sit from the truth.

Renders the board, noiseless, through the true lens at the demo's planned intrinsics views
(`--seed`, the views `board_plan` gives the commissioning, posed by the true rig) and at a sweep
of distances and tilts, detects the corners as commissioning does (`BoardDetector`) and compares
them with the exact projection of the board's corners. For each renderer it prints the corner
error's mean and RMS (px), the RMS of the per-view mean (the part a view shares, which a pose
absorbs only partly), the worst view, and the median render time of a view (ms), as
`metric: value` lines:

- `point`: each pixel the texture at its centre's ray (`area_sampled=False`, the renderer before);
- `area`: each pixel the texture's mean over its footprint (the simulator's renderer);
- `ideal`: 8x8 sub-pixel rays per pixel into a 512-texel-a-square texture, averaged: what the
  sensor integrates, to a few thousandths of a pixel (slow; the reference the others are compared
  with: `*_vs_ideal_rms_px` is the part of a renderer's corner error its sampling adds);

the median time of a view along a moving pass, both renderers interleaved
(`moving_*_render_ms`); and, for `area`, the spread the seeded pixel noise adds to a corner
(`noise_corner_rms_px`), the scale the fixed errors are to be compared with. Run under nice:
it is CPU-bound.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import cv2
import numpy as np

from hil_sim.camera import BOARD_MARGIN_SQUARES, SyntheticCamera
from host.calibration.board import BoardDetector, BoardSpec
from host.commissioning.plan import IMAGE_TARGETS, board_plan
from host.demo.commissioning_phase import board_stations, place_board
from host.demo.rigs import DemoRigs
from host.geometry.camera import CameraModel
from host.geometry.transforms import FloatArray, euler_zyx, invert_T, make_T, transform_points

IDEAL_RAYS = 8  # sub-pixel rays a side
IDEAL_TEXELS = 512  # a square
NO_MAP = np.empty((0, 0), np.float32)  # remap's second map: the first holds (x, y)
Render = Callable[[FloatArray], np.ndarray]
Errors = dict[tuple[int, int], FloatArray]  # (view, corner id) → detected - exact, px


def demo_views(seed: int) -> tuple[CameraModel, BoardSpec, list[FloatArray]]:
    """The true lens, the board and T_c_b of each intrinsics view the quick demo plans."""
    rigs = DemoRigs.make(None, seed, True)
    setup = place_board(rigs, seed)
    stations, _ = board_stations(rigs, setup.s_mm)
    head = rigs.host.head
    limits = ((head.pan_min_rad, head.pan_max_rad), (head.tilt_min_rad, head.tilt_max_rad))
    centre = (setup.T_w_b_surveyed @ np.append(setup.board.centre_mm, 1.0))[:3]
    views = board_plan(
        rigs.host_kinematics(), rigs.host_camera(), centre, stations, IMAGE_TARGETS, limits
    )
    true_rig = rigs.true_kinematics()
    Ts = [
        invert_T(true_rig.T_w_c(v.s_mm, v.pan_rad, v.tilt_rad)) @ setup.placed.T_w_b for v in views
    ]
    return rigs.true_camera(), setup.board, Ts


def sweep_views(spec: BoardSpec) -> list[FloatArray]:
    """The board at 1.5-5 m, tilted 0-40 degrees, turned."""
    Ts = []
    for z in (1500.0, 2500.0, 3500.0, 5000.0):
        for tilt in (0.0, 0.35, 0.7):
            R = euler_zyx(0.2, tilt, 0.1)
            Ts.append(make_T(R, np.array([0.0, 0.0, z]) - R @ spec.centre_mm))
    return Ts


def ideal_renderer(lens: CameraModel, board: cv2.aruco.CharucoBoard) -> Render:
    """IDEAL_RAYS^2 rays a pixel into a fine texture, averaged (noiseless, grey)."""
    k, s = IDEAL_RAYS, IDEAL_TEXELS
    off = (np.arange(k) + 0.5) / k - 0.5
    u = (np.arange(lens.width)[:, None] + off).ravel()
    v = (np.arange(lens.height)[:, None] + off).ravel()
    gu, gv = np.meshgrid(u, v)
    rays = np.ascontiguousarray(lens.undistort_normalized(np.stack([gu, gv], -1)), np.float32)
    cols, rows = board.getChessboardSize()
    m = int(BOARD_MARGIN_SQUARES * s)
    img = board.generateImage((cols * s + 2 * m, rows * s + 2 * m), marginSize=m)
    tex = (20 + np.asarray(img, np.float32) * (215 / 255)).astype(np.uint8)  # as the simulator
    scale = s / float(board.getSquareLength())

    def render(T_c_b: FloatArray) -> np.ndarray:
        Hm = np.column_stack([T_c_b[:3, 0], T_c_b[:3, 1], T_c_b[:3, 3]])
        to_tex = np.array([[scale, 0.0, m - 0.5], [0.0, scale, m - 0.5], [0.0, 0.0, 1.0]])
        M = to_tex @ np.linalg.inv(Hm)
        M = (M / np.linalg.norm(M[2])).astype(np.float32)
        mp = cv2.perspectiveTransform(rays, M)
        fine = cv2.remap(tex, mp, NO_MAP, cv2.INTER_LINEAR, borderValue=110).astype(np.float32)
        out = cv2.resize(fine, (lens.width, lens.height), interpolation=cv2.INTER_AREA)
        return np.asarray(np.clip(np.rint(out), 0, 255), dtype=np.uint8)

    return render


def simulator_renderer(sim: SyntheticCamera, board: cv2.aruco.CharucoBoard) -> Render:
    """The simulator's noiseless board view."""

    def render(T_c_b: FloatArray) -> np.ndarray:
        return sim.render_board(T_c_b, board).image

    return render


def corner_errors(
    det: BoardDetector, lens: CameraModel, Ts: list[FloatArray], render: Render
) -> tuple[Errors, float]:
    """Detected minus exact corner pixels of every view, and the median render time (s)."""
    points = np.asarray(det.board.getChessboardCorners(), np.float64).reshape(-1, 3)
    errs: Errors = {}
    times = []
    for i, T in enumerate(Ts):
        t0 = time.perf_counter()
        img = render(T)
        times.append(time.perf_counter() - t0)
        d = det.detect(img)
        if d is None:
            continue
        uv, _ = lens.project(transform_points(T, points))
        for j, e in zip(d.ids, d.image_points - uv[d.ids], strict=True):
            errs[(i, int(j))] = e
    return errs, float(np.median(times))


def rms(e: FloatArray) -> float:
    """Root mean square of 2-D errors (N, 2)."""
    return float(np.sqrt((e**2).sum(axis=1).mean())) if len(e) else float("nan")


def report(label: str, errs: Errors, render_s: float, views: int) -> None:
    """The `metric: value` lines of one renderer on one view set."""
    e = np.array(list(errs.values()))
    by_view: dict[int, list[FloatArray]] = {}
    for (i, _), x in errs.items():
        by_view.setdefault(i, []).append(x)
    means = np.array([np.mean(v, axis=0) for v in by_view.values()])
    view_rms = [rms(np.array(v)) for v in by_view.values()]
    print(f"{label}_views_detected: {len(by_view)}/{views}")
    print(f"{label}_corners: {len(e)}")
    print(f"{label}_mean_px: {e.mean(0)[0]:+.4f} {e.mean(0)[1]:+.4f}")
    print(f"{label}_rms_px: {rms(e):.4f}")
    print(f"{label}_max_px: {np.abs(e).max():.4f}")
    print(f"{label}_view_mean_rms_px: {rms(means):.4f}")
    print(f"{label}_worst_view_rms_px: {max(view_rms):.4f}")
    print(f"{label}_render_ms: {1e3 * render_s:.1f}")


def versus(label: str, errs: Errors, ref: Errors) -> None:
    """How far a renderer's corners sit from the ideal renderer's."""
    keys = [k for k in errs if k in ref]
    d = np.array([errs[k] - ref[k] for k in keys])
    print(f"{label}_vs_ideal_rms_px: {rms(d):.4f}")


def noise_spread(det: BoardDetector, lens: CameraModel, Ts: list[FloatArray]) -> float:
    """RMS shift of a corner between the noiseless and seeded noisy renders (area sampled)."""
    clean = SyntheticCamera(lens, seed=0, noise_sigma_dn=0.0)
    shifts = []
    for seed in range(3):
        noisy = SyntheticCamera(lens, seed=seed + 1)
        for T in Ts[:5]:
            a = det.detect(clean.render_board(T, det.board).image)
            b = det.detect(noisy.render_board(T, det.board).image)
            if a is None or b is None:
                continue
            _, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
            shifts.append(b.image_points[ib] - a.image_points[ia])
    return rms(np.concatenate(shifts))


def moving_render_ms(lens: CameraModel, board: cv2.aruco.CharucoBoard, T0: FloatArray) -> None:
    """Median ms of a board view along a 300 mm pass (30 frames, as the live camera renders
    while the trolley moves: the footprint changes from frame to frame), both renderers, with
    the seeded noise, alternating frame by frame so that both see the same load."""
    times: dict[bool, list[float]] = {False: [], True: []}
    sims = {a: SyntheticCamera(lens, seed=1, area_sampled=a) for a in (False, True)}
    for i in range(30):
        T = T0.copy()
        T[0, 3] += 10.0 * i
        T[2, 3] += 5.0 * i  # nearer: the scale changes too
        for area, sim in sims.items():
            t0 = time.perf_counter()
            sim.render_board(T, board)
            times[area].append(time.perf_counter() - t0)
    for area, t in times.items():
        print(
            f"moving_{'area' if area else 'point'}_render_ms: {1e3 * float(np.median(t[1:])):.1f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1, help="the demo's seed whose views to render")
    ap.add_argument("--no-ideal", action="store_true", help="skip the slow reference renderer")
    args = ap.parse_args()
    lens, spec, Ts = demo_views(args.seed)
    moving_render_ms(lens, spec.make(), Ts[len(Ts) // 2])
    sets = {f"demo{args.seed}": (lens, spec, Ts)}
    sweep_spec = BoardSpec(squares_x=8, squares_y=6, square_mm=70.0, marker_mm=52.0)
    sets["sweep"] = (CameraModel(), sweep_spec, sweep_views(sweep_spec))
    for name, (cam, sp, views) in sets.items():
        det = BoardDetector(sp)
        found = {}
        for area in (False, True):
            sim = SyntheticCamera(cam, seed=0, noise_sigma_dn=0.0, area_sampled=area)
            errs, t = corner_errors(det, cam, views, simulator_renderer(sim, det.board))
            label = f"{name}_{'area' if area else 'point'}"
            report(label, errs, t, len(views))
            found[label] = errs
        if not args.no_ideal:
            ref, t = corner_errors(det, cam, views, ideal_renderer(cam, det.board))
            report(f"{name}_ideal", ref, t, len(views))
            for label, errs in found.items():
                versus(label, errs, ref)
        print(f"{name}_noise_corner_rms_px: {noise_spread(det, cam, views):.4f}")


if __name__ == "__main__":
    main()
