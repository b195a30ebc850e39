"""The rig description (one schema, one file): read, validated, written atomically with backups.

Public API (used by the daemon, `orbitar sim --rig`, the demo and the commissioning commands):
- `load_rig(path)`, `loads_rig(text)`, `rig_from_dict(table)` → `RigSpec`; `RigError` names keys;
  `current_rig(path)` for the daemon (reread when the file changed; "" is the paper's rig).
- `dumps_rig(spec)`, `save_rig(spec, path)` (atomic, keeps `*.bak`), `backups(path)`.
- `update_rig(path, {"head.m_cr": Pose6(...), ...})`, `with_updates(spec, updates)`: replace
  calibrated blocks (each with σ and `Provenance.now(method, residual, unit, views)`).
- `build_kinematics`, `build_camera`, `build_scene`, `build_track`, `workpiece_pose`.
"""

from host.rig.build import (
    build_camera,
    build_kinematics,
    build_scene,
    build_track,
    travel_limits_mm,
    workpiece_pose,
)
from host.rig.codec import RigError, dumps_rig, load_rig, loads_rig, rig_from_dict, rig_to_dict
from host.rig.schema import (
    INTRINSIC_KEYS,
    CameraSpec,
    HallSpec,
    HeadSpec,
    Intrinsics,
    Marks,
    Pose6,
    Provenance,
    RangefinderSpec,
    RigSpec,
    Scalar,
    Segment,
    SurfaceSpec,
    TrackSpec,
    WorkpieceSpec,
)
from host.rig.store import UPDATABLE, backups, current_rig, save_rig, update_rig, with_updates

__all__ = [
    "INTRINSIC_KEYS",
    "UPDATABLE",
    "CameraSpec",
    "HallSpec",
    "HeadSpec",
    "Intrinsics",
    "Marks",
    "Pose6",
    "Provenance",
    "RangefinderSpec",
    "RigError",
    "RigSpec",
    "Scalar",
    "Segment",
    "SurfaceSpec",
    "TrackSpec",
    "WorkpieceSpec",
    "backups",
    "build_camera",
    "build_kinematics",
    "build_scene",
    "build_track",
    "current_rig",
    "dumps_rig",
    "load_rig",
    "loads_rig",
    "rig_from_dict",
    "rig_to_dict",
    "save_rig",
    "travel_limits_mm",
    "update_rig",
    "with_updates",
    "workpiece_pose",
]
