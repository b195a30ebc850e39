"""Shared registration math: transforms, track, head, camera, workpiece, PnP and models.

Pure numpy/OpenCV with no I/O, imported by the host (calibrated parameters) and by the simulator
(true parameters).
"""

from host.geometry.camera import CameraModel, Projector
from host.geometry.head import M_CR_DEFAULT, Rig, head_rotation
from host.geometry.model import Wireframe, load_model, manipulator_wireframe
from host.geometry.track import Track, runway

__all__ = [
    "M_CR_DEFAULT",
    "CameraModel",
    "Projector",
    "Rig",
    "Track",
    "Wireframe",
    "head_rotation",
    "load_model",
    "manipulator_wireframe",
    "runway",
]
