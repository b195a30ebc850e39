"""Scoring registrations against the simulator's ground truth (never used to register)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from hil_sim.runner import Simulation
from host.demo.world import SceneTruth, SimWorld
from host.frames.registrar import Registration
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import invert_T, transform_points

FloatArray = NDArray[np.float64]
PROBE_DEPTH_MM = 3000.0  # overlay error is quoted for a point 3 m in front of the camera
UM_PER_MM = 1000.0


def true_zero_mm(world: SimWorld) -> float:
    """Where the controller's zero truly is: the plant's arc length less the firmware's position,
    read together under the simulator's lock (the trolley at rest). Scoring only."""

    def simultaneous(sim: Simulation) -> float:
        return float(sim.truth().s_mm - sim.firmware.position_um / UM_PER_MM)

    return float(world.with_truth(simultaneous))


@dataclass(frozen=True)
class Score:
    """Error of one registered frame."""

    s_true_mm: float
    error_px: float
    error_mm: float  # on the workpiece: pixels × depth / focal length


def centre_error(reg: Registration, camera: CameraModel, centroid_p: FloatArray) -> Score | None:
    """Offset of the overlay's projected centre from the real one (nan-free or None)."""
    truth = reg.truth
    if reg.centre_uv is None or not isinstance(truth, SceneTruth):
        return None
    T_c_p = invert_T(truth.T_w_c) @ truth.T_w_p
    pc = transform_points(T_c_p, centroid_p[None, :])
    uv, valid = camera.project(pc)
    if not bool(valid[0]):
        return None
    px = float(np.linalg.norm(reg.centre_uv - uv[0]))
    return Score(truth.s_mm, px, px * float(pc[0, 2]) / camera.fx)


def probe_error(
    T_w_c_est: FloatArray,
    T_w_c_true: FloatArray,
    s_true_mm: float,
    camera: CameraModel,
    depth_mm: float = PROBE_DEPTH_MM,
    true_camera: CameraModel | None = None,
) -> Score:
    """Overlay error of a point on the true optical axis at depth_mm, seen from the estimate.

    The point is where the true lens shows it (`true_camera`, default `camera`); the overlay
    draws it where the host's camera model and pose put it.
    """
    truth_cam = camera if true_camera is None else true_camera
    on_axis_c = np.array([[0.0, 0.0, depth_mm]])
    point_w = transform_points(T_w_c_true, on_axis_c)
    uv_true, _ = truth_cam.project(on_axis_c)
    uv_est, valid = camera.project(transform_points(invert_T(T_w_c_est), point_w))
    px = float(np.linalg.norm(uv_est[0] - uv_true[0])) if bool(valid[0]) else math.inf
    return Score(s_true_mm, px, px * depth_mm / camera.fx)


def aimed_errors(
    regs: tuple[Registration, ...],
    truth: SceneTruth,
    host: tuple[Rig, CameraModel],
    true: tuple[Rig, CameraModel],
    target_w: FloatArray,
) -> list[Score]:
    """Each registration's error as overlay error at 3 m, were the camera aimed at target_w.

    Where the head happens to point changes which pose errors show: a track-position error is
    invisible along the optical axis. Users look at the workpiece, so the registered joint
    values (track position, and the head's reading errors) are carried over to a camera turned
    toward it from the true position, and scored there: the estimate through the host's rig and
    lens, the truth through the simulator's.
    """
    (rig, camera), (true_rig, true_camera) = host, true
    pan, tilt = true_rig.aim(truth.s_mm, target_w)
    T_true = true_rig.T_w_c(truth.s_mm, pan, tilt)
    return [
        probe_error(
            rig.T_w_c(
                reg.s_mm, pan + reg.pan_rad - truth.pan_rad, tilt + reg.tilt_rad - truth.tilt_rad
            ),
            T_true,
            truth.s_mm,
            camera,
            true_camera=true_camera,
        )
        for reg in regs
    ]


def workpiece_errors(
    regs: tuple[Registration, ...],
    truth: SceneTruth,
    host: tuple[Rig, CameraModel],
    true: tuple[Rig, CameraModel],
    point_w: tuple[FloatArray, FloatArray],
) -> list[Score]:
    """Each registration's overlay error on the workpiece, were the camera aimed at it.

    What an operator sees: the model point where the host draws it (its surveyed workpiece,
    through its rig and lens at the registered pose) against where the camera shows it (the
    true workpiece, rig and lens). `point_w` is the point as (host's, true) world position.
    The registered joint values are carried over to a camera turned toward the point from the
    true position, as in `aimed_errors`. Unlike a probe on the optical axis, this leaves out
    what the overlay cannot show: an error of the world frame itself (the board's survey, by
    which the track was placed) is shared by the workpiece surveyed through the same rig.
    """
    (rig, camera), (true_rig, true_camera) = host, true
    host_w, true_w = point_w
    pan, tilt = true_rig.aim(truth.s_mm, true_w)
    seen = transform_points(invert_T(true_rig.T_w_c(truth.s_mm, pan, tilt)), true_w[None, :])
    uv_true, _ = true_camera.project(seen)
    out = []
    for reg in regs:
        T_est = rig.T_w_c(
            reg.s_mm, pan + reg.pan_rad - truth.pan_rad, tilt + reg.tilt_rad - truth.tilt_rad
        )
        uv, valid = camera.project(transform_points(invert_T(T_est), host_w[None, :]))
        px = float(np.linalg.norm(uv[0] - uv_true[0])) if bool(valid[0]) else math.inf
        out.append(Score(truth.s_mm, px, px * float(seen[0, 2]) / true_camera.fx))
    return out


def chain_errors(
    regs: tuple[Registration, ...],
    truth: SceneTruth,
    host: tuple[Rig, CameraModel],
    home_offset_mm: float,
    target_w: FloatArray,
) -> list[Score]:
    """As `aimed_errors`, but against the host's own rig at the true position: the track error.

    The host's rig file and the world disagree by its calibration's world-placement error (the
    board's and walls' survey): a workpiece surveyed through the same rig carries it too, so the
    overlay does not see it. What is left is where the registration puts the trolley along the
    track: its arc length against the true one in the host's own zero (home_offset_mm = the
    host's home less the true zero, constant while the chain does not skip at the zero).
    """
    rig, camera = host
    s_host = truth.s_mm + home_offset_mm
    pan, tilt = rig.aim(s_host, target_w)
    T_ref = rig.T_w_c(s_host, pan, tilt)
    return [
        probe_error(
            rig.T_w_c(
                reg.s_mm, pan + reg.pan_rad - truth.pan_rad, tilt + reg.tilt_rad - truth.tilt_rad
            ),
            T_ref,
            truth.s_mm,
            camera,
        )
        for reg in regs
    ]


def summary(values: list[float]) -> dict[str, float]:
    """Mean, standard deviation, RMS, median and maximum (nan for an empty list)."""
    if not values:
        nan = math.nan
        return {"n": 0, "mean": nan, "std": nan, "rms": nan, "median": nan, "max": nan}
    a = np.asarray(values, dtype=np.float64)
    return {
        "n": int(a.size),
        "mean": float(a.mean()),
        "std": float(a.std(ddof=1)) if a.size > 1 else 0.0,
        "rms": float(np.sqrt(np.mean(a**2))),
        "median": float(np.median(a)),
        "max": float(a.max()),
    }
