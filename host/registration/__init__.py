"""Per-frame registration: pose at the exposure time from sample buffers, and overlay drawing."""

from host.registration.overlay import OverlayStyle, WireframeOverlay, draw_wireframe
from host.registration.pose_buffer import (
    AngleBuffer,
    Lookup,
    LookupStatus,
    PoseLookup,
    PoseSource,
    SampleBuffer,
    TransformBuffer,
)

__all__ = [
    "AngleBuffer",
    "Lookup",
    "LookupStatus",
    "OverlayStyle",
    "PoseLookup",
    "PoseSource",
    "SampleBuffer",
    "TransformBuffer",
    "WireframeOverlay",
    "draw_wireframe",
]
