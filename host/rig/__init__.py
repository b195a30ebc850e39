"""The rig description (one schema, one file): read, validated, written atomically with backups.

Public API (used by the daemon, `orbitar sim --rig`, the demo and the commissioning commands):
- `load_rig(path)`, `loads_rig(text)`, `rig_from_dict(table)` → `RigSpec`; `RigError` names keys;
  `current_rig(path)` for the daemon (reread when the file changed; "" is the paper's rig).
- `dumps_rig(spec)`, `save_rig(spec, path)` (atomic, keeps `*.bak`), `backups(path)`.
- `update_rig(path, {"head.m_cr": Pose6(...), ...})`, `with_updates(spec, updates)`: replace
  calibrated blocks (each with σ and `Provenance.now(method, residual, unit, views)`).
- `covariance_over(spec, names)`, `joint_covariance(blocks, cross, provenance)`,
  `with_block(spec, name, cov, cross, provenance)`: blocks solved or measured together and the
  `[covariance]` block that keeps their cross terms.
- `build_kinematics`, `build_camera`, `build_scene`, `build_track`, `workpiece_pose`;
  `chain_mismatch` (the rig's chain against a controller's build).
The schema's dataclasses and constants are re-exported from `host.rig.schema.__all__`.
"""

from host.rig import schema
from host.rig.build import (
    build_camera,
    build_kinematics,
    build_scene,
    build_track,
    chain_mismatch,
    travel_limits_mm,
    workpiece_pose,
)
from host.rig.codec import RigError, dumps_rig, load_rig, loads_rig, rig_from_dict, rig_to_dict
from host.rig.covariance import block_covariance, covariance_over, joint_covariance, with_block
from host.rig.schema import *  # noqa: F403  (the schema's table of public names)
from host.rig.store import UPDATABLE, backups, current_rig, save_rig, update_rig, with_updates

__all__ = [
    "UPDATABLE",
    "RigError",
    "backups",
    "block_covariance",
    "build_camera",
    "build_kinematics",
    "build_scene",
    "build_track",
    "chain_mismatch",
    "covariance_over",
    "current_rig",
    "dumps_rig",
    "joint_covariance",
    "load_rig",
    "loads_rig",
    "rig_from_dict",
    "rig_to_dict",
    "save_rig",
    "travel_limits_mm",
    "update_rig",
    "with_block",
    "with_updates",
    "workpiece_pose",
]
__all__ += schema.__all__
