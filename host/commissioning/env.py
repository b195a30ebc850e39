"""What a commissioning run needs from the daemon: camera frames, the rig, where to write.

The daemon builds one `CommissioningEnv` and hands it to the control ops. `kinematics` gives
the rig as the daemon knows it now (the rig file if there is one, else the config): the plan
aims with it and the calibration starts from it. `rig_path` is the file a passing calibration
updates (atomically, keeping a backup: host.rig.update_rig); without one a run reports but
writes nothing. Reports go to `report_root`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from host.commissioning.frames import FrameTap
from host.commissioning.jobs import JobBoard
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.rig import build_camera, build_kinematics, load_rig

if TYPE_CHECKING:
    from host.config import Config

DEFAULT_REPORT_ROOT = Path("orbitar-commissioning")


def _no_frames() -> FrameTap | None:
    return None


def _default_kinematics() -> tuple[Rig, CameraModel]:
    return Rig(), CameraModel()


@dataclass
class CommissioningEnv:
    """The daemon's side of a commissioning run."""

    frames: Callable[[], FrameTap | None] = _no_frames
    kinematics: Callable[[], tuple[Rig, CameraModel]] = _default_kinematics
    rig_path: Path | None = None
    report_root: Path = DEFAULT_REPORT_ROOT
    jobs: JobBoard = field(default_factory=JobBoard)

    @classmethod
    def for_rig_file(
        cls, path: Path, frames: Callable[[], FrameTap | None], report_root: Path
    ) -> CommissioningEnv:
        """An env reading its rig fresh from `path` for every run (runs build on each other)."""

        def kinematics() -> tuple[Rig, CameraModel]:
            spec = load_rig(path)
            return build_kinematics(spec), build_camera(spec)

        return cls(frames, kinematics, path, report_root)

    @classmethod
    def for_daemon(cls, config: Config, frames: Callable[[], FrameTap | None]) -> CommissioningEnv:
        """The daemon's default: the rig of its configuration, no rig file to write yet."""

        def kinematics() -> tuple[Rig, CameraModel]:
            from host.service.wiring import build_camera as camera_of
            from host.service.wiring import build_rig

            return build_rig(config), camera_of(config)

        return cls(frames, kinematics)
