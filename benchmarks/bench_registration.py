"""Registration throughput: our projection beside cv2.projectPoints, and the per-frame path.

Run: python benchmarks/bench_registration.py   (prints `metric: value` lines, < 30 s)
"""

from __future__ import annotations

import time
from collections.abc import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from host.geometry.camera import CameraModel, Projector
from host.geometry.head import Rig
from host.geometry.model import Wireframe, manipulator_wireframe
from host.registration.overlay import OverlayStyle, WireframeOverlay
from host.registration.pose_buffer import AngleBuffer, PoseSource, SampleBuffer

FloatArray = NDArray[np.float64]
UInt8Image = NDArray[np.uint8]

N_POINTS = 10_000
PROJECT_REPEATS = 300
FRAME_REPEATS = 500
WIREFRAME_SIDES = 163  # gives the manipulator about 2,000 edges
MS = 1_000_000


def timed_us(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of fn in microseconds after a warm-up."""
    for _ in range(10):
        fn()
    samples = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        samples[i] = time.perf_counter_ns() - t0
    return float(np.median(samples) / 1e3)


def bench_projection() -> None:
    """10k points with distortion (skew 0 so OpenCV is a valid peer)."""
    cam = CameraModel(skew=0.0)
    rng = np.random.default_rng(0)
    z = rng.uniform(2000.0, 5000.0, N_POINTS)
    pts_c = np.stack(
        [rng.uniform(-0.2, 0.2, N_POINTS) * z, rng.uniform(-0.16, 0.16, N_POINTS) * z, z], 1
    )
    rig = Rig()
    T_c_w = rig.T_c_w(1500.0, 0.2, -0.1)
    T_w_c = np.linalg.inv(T_c_w)
    pts_w = pts_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    rvec, _ = cv2.Rodrigues(T_c_w[:3, :3])
    tvec = T_c_w[:3, 3].copy()
    K, dist = cam.K, cam.dist
    proj = Projector(cam, pts_w)

    def ours() -> object:
        return proj.project(rig.T_c_w(1500.0, 0.2, -0.1))

    def peer() -> object:
        return cv2.projectPoints(pts_w, rvec, tvec, K, dist)

    ours_us, cv2_us = timed_us(ours, PROJECT_REPEATS), timed_us(peer, PROJECT_REPEATS)
    uv, _ = proj.project(T_c_w)
    ref = cv2.projectPoints(pts_w, rvec, tvec, K, dist)[0].reshape(-1, 2)
    print(f"points: {N_POINTS}")
    print(f"ours_project_us: {ours_us:.1f}  # includes the pose T_c_w from the rig")
    print(f"cv2_project_us: {cv2_us:.1f}")
    print(f"projection_speedup_vs_cv2: {cv2_us / ours_us:.2f}")
    print(f"max_abs_diff_px: {np.abs(uv.T - ref).max():.3g}")


def bench_frame(antialias: bool) -> None:
    """Pose from the buffers, projection and drawing of a ~2,000-edge model on 1280x1024."""
    cam, rig = CameraModel(), Rig()
    model = manipulator_wireframe(WIREFRAME_SIDES)
    enc, head = SampleBuffer(1), AngleBuffer(2)
    pan, tilt = rig.aim(1200.0, [0.0, 600.0, 800.0])
    for i in range(4096):
        enc.push(i * MS, [800.0 + 0.1 * i])  # 0.1 m/s, 1 kHz
        head.push(i * MS, [pan, tilt])
    src = PoseSource(rig, enc, head, exposure_latency_ns=5 * MS)
    overlay = WireframeOverlay(cam, model)
    frame = np.full((cam.height, cam.width, 3), 110, np.uint8)
    style = OverlayStyle((0, 255, 0), 1, antialias)
    times = np.empty(FRAME_REPEATS)
    drawn = 0
    for i in range(FRAME_REPEATS):
        t_frame = 4096 * MS + 5 * MS + (i % 10) * 100_000
        t0 = time.perf_counter_ns()
        pose = src.pose_at(t_frame)
        assert pose.T_w_c is not None
        drawn = overlay.draw(frame, np.linalg.inv(pose.T_w_c), style)
        times[i] = time.perf_counter_ns() - t0
    ms = times / 1e6
    tag = "_aa" if antialias else ""
    peer = cv2_frame_ms(src, cam, model, frame, antialias)
    if not antialias:
        print(f"frame_edges: {len(model.edges)}")
        print(f"frame_segments_drawn: {drawn}")
    print(f"frame_ms_median{tag}: {np.median(ms):.3f}")
    print(f"cv2_frame_ms_median{tag}: {np.median(peer):.3f}  # projectPoints + polylines")
    print(f"frame_ms_p99{tag}: {np.percentile(ms, 99):.3f}")
    print(f"cv2_frame_ms_p99{tag}: {np.percentile(peer, 99):.3f}")


def cv2_frame_ms(
    src: PoseSource, cam: CameraModel, model: Wireframe, frame: UInt8Image, antialias: bool
) -> FloatArray:
    """The peer: the same pose, cv2.projectPoints of every vertex, cv2.polylines of every edge."""
    K, dist = cam.K, cam.dist
    times = np.empty(FRAME_REPEATS)
    line = cv2.LINE_AA if antialias else cv2.LINE_8
    for i in range(FRAME_REPEATS):
        t_frame = 4096 * MS + 5 * MS + (i % 10) * 100_000
        t0 = time.perf_counter_ns()
        pose = src.pose_at(t_frame)
        assert pose.T_w_c is not None
        T_c_w = np.linalg.inv(pose.T_w_c)
        rvec, _ = cv2.Rodrigues(T_c_w[:3, :3])
        uv = cv2.projectPoints(model.vertices, rvec, T_c_w[:3, 3], K, dist)[0].reshape(-1, 2)
        segments = np.round(uv[model.edges]).astype(np.int32)
        cv2.polylines(frame, list(segments), False, (0, 255, 0), 1, line)
        times[i] = time.perf_counter_ns() - t0
    return times / 1e6


def main() -> None:
    """Run both benchmarks."""
    bench_projection()
    bench_frame(antialias=False)
    bench_frame(antialias=True)


if __name__ == "__main__":
    main()
