"""Per-frame registration: exposure time → camera pose → projected model → overlay.

This is the work the frame loop runs for every frame, off the event loop. It uses only what a
real rig has: the frame's timestamp, the pose buffers fed by the controller link, the
calibrated rig and camera, and the workpiece pose measured at set-up.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.model import Wireframe
from host.geometry.transforms import invert_T, transform_points
from host.registration.overlay import OverlayStyle, WireframeOverlay
from host.registration.pose_buffer import LookupStatus, PoseSource

FloatArray = NDArray[np.float64]
WorkpiecePose = Callable[[int], FloatArray]  # exposure time (host ns) → T_w_p


@dataclass(frozen=True)
class Registration:
    """What the host made of one frame."""

    index: int
    exposure_ns: int
    status: LookupStatus
    T_w_c: FloatArray | None
    s_mm: float
    pan_rad: float
    tilt_rad: float
    centre_uv: FloatArray | None  # projected model centroid, pixels
    segments: int
    image: NDArray[np.uint8] | None  # the frame with the overlay drawn, when drawing
    truth: Any  # the source's ground truth, passed through for scoring only
    frame: NDArray[np.uint8] | None = None  # the captured image as it came (not copied)


class Registrar:
    """Callable that registers one frame; holds the reusable projection buffers."""

    def __init__(
        self,
        poses: PoseSource,
        camera: CameraModel,
        model: Wireframe,
        workpiece: WorkpiecePose,
        draw: bool = True,
        style: OverlayStyle | None = None,
    ) -> None:
        self.poses = poses
        self.camera = camera
        self.model = model
        self.workpiece = workpiece
        self.draw = draw
        self.style = style or OverlayStyle(thickness=2)
        self._overlay = WireframeOverlay(camera, model)
        self._centroid_p = model.vertices.mean(axis=0)

    def __call__(self, frame: Frame) -> Registration:
        """Register one frame; a stale or missing pose yields no overlay, never a guess."""
        pose = self.poses.pose_at(frame.exposure_ns)
        if not pose.ok or pose.T_w_c is None:
            return Registration(
                frame.index,
                frame.exposure_ns,
                pose.status,
                None,
                pose.s_mm,
                pose.pan_rad,
                pose.tilt_rad,
                None,
                0,
                None,
                frame.truth,
                frame.image,
            )
        T_c_p = invert_T(pose.T_w_c) @ self.workpiece(pose.t_exposure_ns)
        uv, valid = self.camera.project(transform_points(T_c_p, self._centroid_p[None, :]))
        centre = uv[0] if bool(valid[0]) else None
        image = None
        segments = 0
        if self.draw:
            image = frame.image.copy()
            segments = self._overlay.draw(image, T_c_p, self.style)
        return Registration(
            frame.index,
            frame.exposure_ns,
            LookupStatus.OK,
            pose.T_w_c,
            pose.s_mm,
            pose.pan_rad,
            pose.tilt_rad,
            centre,
            segments,
            image,
            frame.truth,
            frame.image,
        )
