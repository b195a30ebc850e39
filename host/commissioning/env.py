"""What a commissioning run needs from the daemon: camera frames, the rig, where to write.

The daemon builds one `CommissioningEnv` and hands it to the control ops. `kinematics` gives
the rig as the daemon knows it now (the rig file if there is one, else the config): the plan
aims with it and the calibration starts from it. `rig_path` is the file a passing calibration
updates (atomically, keeping a backup: host.rig.update_rig); without one a run reports but
writes nothing. Reports go to `report_root`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from host.commissioning.frames import FrameTap, RangeTap
from host.commissioning.jobs import JobBoard
from host.experiments.budget import BudgetInputs, inputs_from_rig, overlay_sigma
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import load_model, manipulator_wireframe
from host.geometry.rangefinder import RangeScene
from host.geometry.transforms import FloatArray
from host.rig import RigSpec, build_camera, build_kinematics, build_scene, load_rig
from host.rig.store import current_rig

if TYPE_CHECKING:
    from host.config import Config

log = logging.getLogger(__name__)

DEFAULT_REPORT_ROOT = Path("orbitar-commissioning")
BUILTIN_MODEL = "builtin:manipulator"
BUDGET_CACHE_S = 2.0
REPORT_DIR = "commissioning"  # beside the rig file


@dataclass(frozen=True)
class BudgetValue:
    """One evaluation of the error budget: σ (None: unknown), where, and when."""

    sigma_px: float | None
    pose: tuple[float, float, float]  # controller position (mm), pan, tilt (rad)
    pose_at_s: float  # host monotonic time of the controller data the pose came from
    computed_at_s: float


def _budget_key(pose: tuple[float, float, float]) -> tuple[int, int, int]:
    """Poses within 1 mm and 1 mrad share a budget."""
    return round(pose[0]), round(pose[1] * 1e3), round(pose[2] * 1e3)


def _no_frames() -> FrameTap | None:
    return None


def _default_kinematics() -> tuple[Rig, CameraModel]:
    return Rig(), CameraModel()


def _no_scene() -> RangeScene | None:
    return None


def _no_home() -> float:
    return 0.0


def _no_camera_cov() -> FloatArray | None:
    return None


def _no_budget() -> tuple[BudgetInputs, FloatArray] | None:
    return None


def _nominal_spec() -> RigSpec:
    return RigSpec()


@dataclass
class CommissioningEnv:
    """The daemon's side of a commissioning run."""

    frames: Callable[[], FrameTap | None] = _no_frames
    kinematics: Callable[[], tuple[Rig, CameraModel]] = _default_kinematics
    rig_path: Path | None = None
    report_root: Path = DEFAULT_REPORT_ROOT
    jobs: JobBoard = field(default_factory=JobBoard)
    home_s_mm: Callable[[], float] = _no_home  # track arc length of the controller's zero
    # 10×10 covariance of the camera in use (host.rig.INTRINSIC_KEYS order), None if unknown
    camera_cov: Callable[[], FloatArray | None] = _no_camera_cov
    # the error budget's inputs and the model points it is evaluated on (None: no budget)
    budget: Callable[[], tuple[BudgetInputs, FloatArray] | None] = _no_budget
    ranges: Callable[[], RangeTap | None] | None = None  # the controller's rangefinder readings
    scene: Callable[[], RangeScene | None] = _no_scene  # the rig file's surveyed surfaces
    # the daemon's own pose source: frame stamp → (s_mm, pan, tilt), None when it has none
    pose_at: Callable[[int], tuple[float, float, float] | None] | None = None
    latency_ms: Callable[[], float] = _no_home  # the exposure latency the pose source applies
    # called after a passing run wrote the rig file: the daemon rereads it (as on SIGHUP)
    after_write: Callable[[], Awaitable[Any]] | None = None
    # the rig description as it stands (σ of every block: the rangefinder runs propagate them)
    spec: Callable[[], RigSpec] = _nominal_spec

    _budget_last: BudgetValue | None = field(default=None, init=False, repr=False)
    _budget_task: asyncio.Task[None] | None = field(default=None, init=False, repr=False)

    def overlay_budget(self, snapshot: Mapping[str, Any]) -> dict[str, Any]:
        """The status op's budget fields: the last predicted overlay σ (px; None when unknown),
        the pose it was evaluated at and that pose's age (s).

        Never computed on the caller's loop (tens of milliseconds on a loaded machine starved
        the link's heartbeats): a pose that moved by 1 mm or 1 mrad, or a value older than
        BUDGET_CACHE_S (a calibration may have rewritten the rig file), starts one evaluation
        in a worker thread, and a later status reports it.
        """
        pos, head = snapshot.get("position_mm"), snapshot.get("head_rad")
        now = time.monotonic()
        if pos is not None and head:
            pose = (float(pos), float(head[0]), float(head[1]))
            age = snapshot.get("age_s")
            self._refresh(pose, now - (float(age) if isinstance(age, int | float) else 0.0))
        last = self._budget_last
        if last is None:
            return {
                "overlay_sigma_px": None,
                "overlay_sigma_pose": None,
                "overlay_sigma_age_s": None,
            }
        s_mm, pan, tilt = last.pose
        return {
            "overlay_sigma_px": last.sigma_px,
            "overlay_sigma_pose": {"position_mm": s_mm, "pan_rad": pan, "tilt_rad": tilt},
            "overlay_sigma_age_s": round(now - last.pose_at_s, 3),
        }

    async def aclose(self) -> None:
        """Stop waiting on a budget evaluation (its worker thread ends on its own)."""
        task, self._budget_task = self._budget_task, None
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def _refresh(self, pose: tuple[float, float, float], pose_at_s: float) -> None:
        """Start an evaluation at `pose` unless one runs or the last one still holds."""
        if self._budget_task is not None and not self._budget_task.done():
            return
        last = self._budget_last
        fresh = last is not None and time.monotonic() - last.computed_at_s < BUDGET_CACHE_S
        if fresh and last is not None and _budget_key(last.pose) == _budget_key(pose):
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no loop (a synchronous caller): the last value stands
            return

        async def evaluate() -> None:
            value = await asyncio.to_thread(self._overlay_sigma, *pose)
            self._budget_last = BudgetValue(value, pose, pose_at_s, time.monotonic())

        self._budget_task = loop.create_task(evaluate())

    def _overlay_sigma(self, pos: float, pan: float, tilt: float) -> float | None:
        """The budget at one pose (in a worker thread: the rig file is read there too)."""
        head = (pan, tilt)
        try:
            got = self.budget()
            if got is None:
                return None
            inputs, points = got
            s_mm = float(pos) + self.home_s_mm()
            b = overlay_sigma(inputs, s_mm, float(head[0]), float(head[1]), points)
        except Exception as exc:  # a status must never fail on a bad rig file
            log.warning("overlay budget unavailable", extra={"kv": {"error": exc}})
            return None
        return round(b.sigma_px, 3) if np.isfinite(b.sigma_px) else None

    @classmethod
    def for_rig(
        cls,
        load: Callable[[], RigSpec],
        path: Path | None,
        frames: Callable[[], FrameTap | None],
        report_root: Path,
    ) -> CommissioningEnv:
        """An env reading its rig through `load` for every run (so runs build on each other)."""

        def kinematics() -> tuple[Rig, CameraModel]:
            spec = load()
            return build_kinematics(spec), build_camera(spec)

        def home() -> float:
            return float(load().track.home.value)

        def camera_cov() -> FloatArray:
            intr = load().camera.intrinsics
            if intr.covariance is not None:
                return np.array(intr.covariance, dtype=np.float64)
            return np.diag(np.square(intr.sigma))

        def budget() -> tuple[BudgetInputs, FloatArray]:
            spec = load()
            model = spec.workpiece.model
            wire = manipulator_wireframe() if model == BUILTIN_MODEL else load_model(model)
            return inputs_from_rig(spec), wire.vertices

        def latency() -> float:
            return float(load().camera.latency.value)

        def scene() -> RangeScene | None:
            return build_scene(load())

        return cls(frames, kinematics, path, report_root, home_s_mm=home, camera_cov=camera_cov,
                   budget=budget, latency_ms=latency, scene=scene, spec=load)  # fmt: skip

    @classmethod
    def for_rig_file(
        cls, path: Path, frames: Callable[[], FrameTap | None], report_root: Path
    ) -> CommissioningEnv:
        """An env on a rig file, read fresh for every run."""
        return cls.for_rig(lambda: load_rig(path), path, frames, report_root)

    @classmethod
    def for_daemon(cls, config: Config, frames: Callable[[], FrameTap | None]) -> CommissioningEnv:
        """The daemon's: its `[rig] path` (written by passing runs; reports beside it), or the
        paper's nominal rig when the path is empty (runs report, nothing is written)."""
        if not config.rig.path:
            return cls.for_rig(RigSpec, None, frames, DEFAULT_REPORT_ROOT)
        path = Path(config.rig.path)
        return cls.for_rig(lambda: current_rig(path), path, frames, path.parent / REPORT_DIR)
