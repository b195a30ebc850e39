"""`[rangefinder]`: where the rangefinder sits on the head, and the surfaces it may read.

Surveyed surfaces turn rangefinder readings into absolute references of the track position for
the drift correction (host.fusion.range_fix); with none listed, readings are only passed on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from host.config_fields import parse_rigid4, parse_vector3, spec

IDENTITY_4 = (
    (1.0, 0.0, 0.0, 0.0),
    (0.0, 1.0, 0.0, 0.0),
    (0.0, 0.0, 1.0, 0.0),
    (0.0, 0.0, 0.0, 1.0),
)


@dataclass(frozen=True)
class SurfaceConfig:
    """A surveyed flat surface: a wall (radius 0 = unbounded), a pillar face, a target board."""

    name: str = spec("", doc="a name for logs and statistics")
    point_mm: tuple[float, float, float] = spec(
        (0.0, 0.0, 0.0), parse=parse_vector3, doc="a point on the surface, world frame"
    )
    normal: tuple[float, float, float] = spec(
        (0.0, 0.0, 1.0), parse=parse_vector3, doc="the surface's normal, world frame"
    )
    radius_mm: float = spec(
        0.0, lo=0.0, hi=1e6, doc="extent around point_mm; 0 for an unbounded wall"
    )


@dataclass(frozen=True)
class RangefinderConfig:
    """The rangefinder on the head and the surveyed surfaces it can read."""

    mount: tuple[tuple[float, ...], ...] = spec(
        IDENTITY_4,
        parse=parse_rigid4,
        doc="rangefinder in the head frame (T_r_l), rows, mm; the beam runs along its +z",
    )
    noise_mm: float = spec(1.0, lo=0.001, hi=1000.0, doc="σ of one reading")
    surfaces: tuple[SurfaceConfig, ...] = field(default_factory=tuple)


SURFACES_EXAMPLE = """# Surveyed surfaces the rangefinder may read (none: readings unused), e.g.:
# [[rangefinder.surfaces]]
# name = "north wall"
# point_mm = [6000.0, 0.0, 0.0]
# normal = [-1.0, 0.0, 0.0]
# radius_mm = 0.0"""


def surface_problems(index: int, surface: SurfaceConfig) -> list[str]:
    """What is wrong with one surface, as `key = value: reason` lines."""
    # Imported here: the geometry needs numpy, which `orbitar status` never loads for a config.
    from host.geometry.rangefinder import unit_normal

    key = f"rangefinder.surfaces[{index}]"
    problems = []
    if not surface.name:
        problems.append(f"{key}.name: required")
    try:
        unit_normal(surface.normal)  # the geometry's own rule
    except ValueError as exc:
        problems.append(f"{key}.normal = {list(surface.normal)}: {exc}")
    return problems
