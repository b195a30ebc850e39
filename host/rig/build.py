"""From a `RigSpec` to the geometry objects the host computes with (and the simulator renders with).

The daemon builds these from the calibrated rig file; `orbitar sim --rig` and the demo build the
same objects from the true rig (nominal + seeded tolerances), so host and simulator share one
track module, one camera model and one rangefinder model.
"""

from __future__ import annotations

import math

import numpy as np

from host.geometry.camera import CameraModel
from host.geometry.head import Rig, orthonormalize_T
from host.geometry.rangefinder import RangeScene, Surface
from host.geometry.track import Track
from host.geometry.transforms import FloatArray
from host.rig.schema import ChainSpec, RigSpec, TrackSpec

OPEN_TRACK_MARGIN_MM = 100.0  # an open track's limit switches sit this far inside its ends
LOOP_TRAVEL_BEFORE_MM = 400.0  # a closed loop's cable carrier: travel before s = 0 ...
LOOP_TRAVEL_AFTER_MM = 500.0  # ... and past one lap


def build_track(track: TrackSpec) -> Track:
    """The track geometry placed in the world (ValueError names what is wrong)."""
    segments = [s.as_geometry() for s in track.segments]
    return Track.from_config(segments, track.placement.matrix, track.closed)


def build_kinematics(spec: RigSpec) -> Rig:
    """Track, M_cr and rangefinder mount (rotation blocks made exactly orthonormal)."""
    return Rig(
        track=build_track(spec.track),
        T_r_c=orthonormalize_T(spec.head.m_cr.matrix),
        T_r_l=orthonormalize_T(spec.rangefinder.mount.matrix),
    )


def build_camera(spec: RigSpec) -> CameraModel:
    """The camera model: intrinsics and resolution."""
    i, cam = spec.camera.intrinsics.as_dict(), spec.camera
    return CameraModel(
        i["fx"], i["fy"], i["skew"], i["u0"], i["v0"],
        i["k1"], i["k2"], i["p1"], i["p2"], i["k3"], cam.width, cam.height,
    )  # fmt: skip


def build_scene(spec: RigSpec) -> RangeScene | None:
    """The surveyed surfaces as a rangefinder scene, or None when there are none."""
    if not spec.hall.surfaces:
        return None
    return RangeScene(
        tuple(
            Surface(s.name, s.point_mm, s.normal, s.radius_mm or math.inf)
            for s in spec.hall.surfaces
        )
    )


def workpiece_pose(spec: RigSpec) -> FloatArray:
    """T_w_p: the workpiece frame in the world."""
    return np.array(spec.workpiece.frame.matrix)


def travel_limits_mm(track: TrackSpec) -> tuple[float, float]:
    """Unwrapped arc lengths of the two limit switches."""
    length = track.length_mm
    closed = build_track(track).closed
    lo_default = -LOOP_TRAVEL_BEFORE_MM if closed else OPEN_TRACK_MARGIN_MM
    hi_default = length + (LOOP_TRAVEL_AFTER_MM if closed else -OPEN_TRACK_MARGIN_MM)
    lo = track.travel_min_mm if track.travel_min_mm is not None else lo_default
    hi = track.travel_max_mm if track.travel_max_mm is not None else hi_default
    return lo, hi


def chain_mismatch(chain: ChainSpec, teeth: int, pitch_mm: float) -> str:
    """How a controller built for `teeth` × `pitch_mm` differs from the rig's chain ("" if not)."""
    problems = []
    if teeth != chain.sprocket_teeth:
        problems.append(f"sprocket {teeth} teeth, the rig file's {chain.sprocket_teeth}")
    if abs(pitch_mm - chain.pitch_mm) > 1e-3:
        problems.append(f"pitch {pitch_mm:g} mm, the rig file's {chain.pitch_mm:g} mm")
    return "; ".join(problems)
