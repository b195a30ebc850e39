"""The rangefinder's beam and the surveyed surfaces it can read.

The rangefinder rides on the head beside the camera. Its frame `l` sits in the head frame at
`Rig.T_r_l` (calibrated like M_cr) and the beam leaves its origin along +z_l. A surveyed surface
is a flat patch fixed in the world — a hall wall, a pillar's face, a target board — given by a
point, a unit normal and a radius (infinite for a wall). `RangeScene.cast` returns the nearest
surface a beam meets: the host predicts readings with it (the calibrated rig) and the simulator
produces them with it (the true rig), so both sides share one model of what a reading means.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from host.geometry.head import Rig
from host.geometry.transforms import ArrayLike, FloatArray

PARALLEL_COS = 1e-9  # a beam this close to parallel to a surface never meets it


def unit_normal(normal: ArrayLike) -> tuple[float, float, float]:
    """A surface normal scaled to length 1; ValueError unless it has a usable direction."""
    n = np.asarray(normal, dtype=np.float64)
    with np.errstate(over="ignore"):  # a length that overflows is as unusable as zero
        norm = float(np.linalg.norm(n))
    if n.shape != (3,) or not math.isfinite(norm) or norm < 1e-9:
        raise ValueError("must be a non-zero vector")
    x, y, z = (float(v) for v in n / norm)
    return x, y, z


@dataclass(frozen=True)
class Surface:
    """A flat surveyed patch: every point within radius_mm of point_w on the plane ⟂ normal_w."""

    name: str
    point_w: tuple[float, float, float]
    normal_w: tuple[float, float, float]
    radius_mm: float = math.inf

    def __post_init__(self) -> None:
        try:
            normal = unit_normal(self.normal_w)
        except ValueError as exc:
            raise ValueError(f"surface {self.name!r}: the normal {exc}") from None
        if not self.radius_mm > 0.0:
            raise ValueError(f"surface {self.name!r}: radius_mm must be > 0")
        object.__setattr__(self, "normal_w", normal)


@dataclass(frozen=True)
class Hit:
    """Where a beam meets the scene: the nearest surface, and how cleanly."""

    distance_mm: float
    surface: int  # index into RangeScene.surfaces
    cos_incidence: float  # |beam · normal|: 1 head-on, → 0 grazing
    next_mm: float  # distance to the next surface along the same beam (inf when none)


@dataclass(frozen=True)
class RangeScene:
    """The surveyed surfaces a rangefinder reading may be matched against."""

    surfaces: tuple[Surface, ...] = ()

    def cast(self, origin_w: ArrayLike, direction_w: ArrayLike) -> Hit | None:
        """The nearest surface in front of the beam, or None when it meets none."""
        o = np.asarray(origin_w, dtype=np.float64)
        d = np.asarray(direction_w, dtype=np.float64)
        d = d / np.linalg.norm(d)
        hits: list[tuple[float, int, float]] = []
        for i, surf in enumerate(self.surfaces):
            n = np.asarray(surf.normal_w)
            cos = float(n @ d)
            if abs(cos) < PARALLEL_COS:
                continue
            t = float(n @ (np.asarray(surf.point_w) - o)) / cos
            if t <= 0.0:
                continue
            if math.isfinite(surf.radius_mm):
                off = o + t * d - np.asarray(surf.point_w)
                if float(off @ off) > surf.radius_mm**2:
                    continue
            hits.append((t, i, abs(cos)))
        if not hits:
            return None
        hits.sort()
        t, i, cos = hits[0]
        return Hit(t, i, cos, hits[1][0] if len(hits) > 1 else math.inf)

    def names(self) -> Sequence[str]:
        """Surface names, by index."""
        return [s.name for s in self.surfaces]


def beam_w(rig: Rig, s_mm: float, pan_rad: float, tilt_rad: float) -> tuple[FloatArray, FloatArray]:
    """Origin and unit direction of the rangefinder's beam in the world."""
    T = rig.T_w_r(s_mm, pan_rad, tilt_rad) @ rig.T_r_l
    return T[:3, 3].copy(), T[:3, 2].copy()


def range_at(
    rig: Rig, scene: RangeScene, s_mm: float, pan_rad: float, tilt_rad: float
) -> Hit | None:
    """What the rangefinder reads at a pose: the nearest surface along its beam."""
    origin, direction = beam_w(rig, s_mm, pan_rad, tilt_rad)
    return scene.cast(origin, direction)


def hall_walls(
    x_mm: tuple[float, float], y_mm: tuple[float, float], floor_z_mm: float = 0.0
) -> tuple[Surface, ...]:
    """The four walls and the floor of a rectangular hall, normals facing inward."""
    (x0, x1), (y0, y1) = x_mm, y_mm
    if not (x0 < x1 and y0 < y1):
        raise ValueError("hall bounds must be (low, high) with low < high")
    return (
        Surface("wall x-", (x0, 0.0, 0.0), (1.0, 0.0, 0.0)),
        Surface("wall x+", (x1, 0.0, 0.0), (-1.0, 0.0, 0.0)),
        Surface("wall y-", (0.0, y0, 0.0), (0.0, 1.0, 0.0)),
        Surface("wall y+", (0.0, y1, 0.0), (0.0, -1.0, 0.0)),
        Surface("floor", (0.0, 0.0, floor_z_mm), (0.0, 0.0, 1.0)),
    )
