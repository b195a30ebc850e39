"""A rangefinder that reads surveyed surfaces: the true rig's beam cast into a `RangeScene`.

The scenario's default rangefinder sees a level floor; a scene with walls, pillars or target
boards gives readings that depend on where the trolley is along the track — the absolute
reference the host's chain filter can use. The same `host.geometry.rangefinder` model serves the
host's prediction (calibrated rig) and this truth (true rig).
"""

from __future__ import annotations

from hil_sim.scenario import RangeTarget
from host.geometry.head import Rig
from host.geometry.rangefinder import RangeScene, range_at


def surveyed_target(rig: Rig, scene: RangeScene) -> RangeTarget:
    """A `RangefinderConfig.target`: true distance to the nearest surface along the beam."""

    def target(s_mm: float, pan_rad: float, tilt_rad: float) -> float | None:
        hit = range_at(rig, scene, s_mm, pan_rad, tilt_rad)
        return None if hit is None else hit.distance_mm

    return target
