"""Overhead track geometry: straights and arcs, arc length s → trolley pose T_w_t(s).

Frames (DESIGN.md, paper §3.1.1):
- world `w`: floor plane z = 0, z up. For `runway()` the origin is on the floor below the centre
  of the runway, x along the long side.
- track `track`: the plane of the track; the path starts at its origin heading +x and turns in its
  x-y plane (positive arc angle = left turn, counter-clockwise seen from +z). `T_w_track` places
  it in the world; for the runway it is 4 m above the floor.
- trolley `t`: origin on the track centre line at s, x along the direction of travel, z down toward
  the floor, y = z × x (to the right of travel). z down makes a camera with M_cr ≈ I (eq. 14)
  and zero head angles look straight at the floor, where the workpiece is.

Used by host (calibrated parameters) and simulator (true parameters): pure math, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.geometry.transforms import ArrayLike, FloatArray, make_T

CLOSURE_TOL_MM = 1e-6  # end-to-start gap under which a track counts as a closed loop
CLOSURE_TOL_RAD = 1e-9
RUNWAY_LENGTH_MM = 6000.0  # paper §5: runway 6 m x 3 m, corner radius 1 m, 4 m above the floor
RUNWAY_WIDTH_MM = 3000.0
RUNWAY_CORNER_RADIUS_MM = 1000.0
RUNWAY_HEIGHT_MM = 4000.0
_DOWN_Z = np.array([0.0, 0.0, -1.0])


@dataclass(frozen=True)
class Segment:
    """One piece of track: a straight (curvature 0) or a circular arc of signed curvature."""

    length_mm: float
    curvature_per_mm: float

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Segment:
        """Parse {"kind": "straight", "length_mm"} or {"kind": "arc", "radius_mm", "angle_deg"}."""
        kind = d.get("kind")
        if kind == "straight":
            length = float(d["length_mm"])
            if not length > 0.0:
                raise ValueError(f"straight length_mm must be > 0, got {length}")
            return cls(length, 0.0)
        if kind == "arc":
            radius, angle = float(d["radius_mm"]), math.radians(float(d["angle_deg"]))
            if not radius > 0.0 or angle == 0.0:
                raise ValueError(f"arc needs radius_mm > 0 and angle_deg != 0, got {dict(d)}")
            return cls(radius * abs(angle), math.copysign(1.0 / radius, angle))
        raise ValueError(f"segment kind must be 'straight' or 'arc', got {kind!r}")


@dataclass(frozen=True, eq=False)
class Track:
    """A planar path of segments placed in the world by T_w_track; closed loops wrap s."""

    segments: tuple[Segment, ...]
    T_w_track: FloatArray = field(default_factory=lambda: np.eye(4))
    closed: bool = False
    _s0: FloatArray = field(init=False, repr=False)
    _xy0: FloatArray = field(init=False, repr=False)
    _h0: FloatArray = field(init=False, repr=False)
    _k: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.segments:
            raise ValueError("a track needs at least one segment")
        object.__setattr__(self, "T_w_track", np.asarray(self.T_w_track, dtype=np.float64))
        lengths = np.array([g.length_mm for g in self.segments])
        k = np.array([g.curvature_per_mm for g in self.segments])
        s0 = np.concatenate([[0.0], np.cumsum(lengths)])
        h0 = np.concatenate([[0.0], np.cumsum(lengths * k)])
        xy0 = np.zeros((len(lengths) + 1, 2))
        for i, (L, kk) in enumerate(zip(lengths, k, strict=True)):
            xy0[i + 1] = xy0[i] + _advance(L, kk, h0[i])
        object.__setattr__(self, "_s0", s0)
        object.__setattr__(self, "_xy0", xy0)
        object.__setattr__(self, "_h0", h0)
        object.__setattr__(self, "_k", k)
        if self.closed and not self.closes():
            raise ValueError(
                f"track marked closed but its end is {self.closure_gap_mm():.3g} mm and "
                f"{self.closure_heading_error_rad():.3g} rad from its start"
            )

    @classmethod
    def from_config(
        cls,
        segments: Sequence[Mapping[str, Any]],
        T_w_track: ArrayLike | None = None,
        closed: bool | None = None,
    ) -> Track:
        """Build from segment dicts; closed=None means closed exactly when the path closes."""
        segs = tuple(Segment.from_dict(d) for d in segments)
        T = np.eye(4) if T_w_track is None else np.asarray(T_w_track, dtype=np.float64)
        probe = cls(segs, T, closed=False)
        return cls(segs, T, closed=probe.closes() if closed is None else closed)

    @property
    def length_mm(self) -> float:
        """Total arc length of the path."""
        return float(self._s0[-1])

    def closure_gap_mm(self) -> float:
        """Distance from the end of the path back to its start."""
        return float(np.linalg.norm(self._xy0[-1]))

    def closure_heading_error_rad(self) -> float:
        """Heading mismatch between end and start, wrapped to [0, π]."""
        return abs(math.remainder(float(self._h0[-1]), 2.0 * math.pi))

    def closes(self) -> bool:
        """Whether the end pose coincides with the start pose."""
        gap_ok = self.closure_gap_mm() < CLOSURE_TOL_MM
        return gap_ok and self.closure_heading_error_rad() < CLOSURE_TOL_RAD

    def wrap(self, s_mm: ArrayLike) -> FloatArray:
        """Arc length into [0, length): modulo on a closed loop, range-checked on an open path."""
        s = np.asarray(s_mm, dtype=np.float64)
        if self.closed:
            out: FloatArray = np.mod(s, self.length_mm)
            return out
        if np.any(s < 0.0) or np.any(s > self.length_mm) or np.any(~np.isfinite(s)):
            raise ValueError(f"s outside the open track [0, {self.length_mm}] mm")
        return s

    def planar(self, s_mm: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Position (...,2) in the track plane and heading (rad from +x) at arc length s."""
        s = self.wrap(s_mm)
        i = np.clip(np.searchsorted(self._s0, s, side="right") - 1, 0, len(self.segments) - 1)
        d = s - self._s0[i]
        k, h0 = self._k[i], self._h0[i]
        xy = self._xy0[i] + _advance(d, k, h0)
        return xy, h0 + k * d

    def local_pose(self, s_mm: ArrayLike) -> FloatArray:
        """T_track_t(s): trolley pose in the track frame, shape s.shape + (4, 4)."""
        xy, h = self.planar(s_mm)
        c, sn = np.cos(h), np.sin(h)
        R = np.zeros((*h.shape, 3, 3))
        R[..., 0, 0], R[..., 1, 0] = c, sn  # x_t: direction of travel
        R[..., 0, 1], R[..., 1, 1] = sn, -c  # y_t = z_t × x_t, to the right of travel
        R[..., :, 2] = _DOWN_Z  # z_t: down toward the floor
        p = np.concatenate([xy, np.zeros((*h.shape, 1))], axis=-1)
        return make_T(R, p)

    def pose(self, s_mm: ArrayLike) -> FloatArray:
        """T_w_t(s): trolley pose in the world, shape s.shape + (4, 4)."""
        out: FloatArray = self.T_w_track @ self.local_pose(s_mm)
        return out

    def position(self, s_mm: ArrayLike) -> FloatArray:
        """Trolley origin in the world (...,3) at arc length s."""
        return self.pose(s_mm)[..., :3, 3]

    def with_origin(self, T_w_track: ArrayLike) -> Track:
        """The same path placed in the world by another T_w_track (e.g. a calibrated one)."""
        return Track(self.segments, np.asarray(T_w_track, dtype=np.float64), self.closed)

    def with_arc_radius_change(self, d_radius_mm: float) -> Track:
        """The same path with every arc's radius changed by `d_radius_mm`, each turning the same
        angle (arcs bent on one jig); open when the changed path no longer closes."""
        segs = tuple(_bent(g, d_radius_mm) for g in self.segments)
        probe = Track(segs, self.T_w_track, closed=False)
        return Track(segs, self.T_w_track, self.closed and probe.closes())


def _bent(g: Segment, d_radius_mm: float) -> Segment:
    """A segment with its radius changed (a straight as it is), turning the same angle."""
    if g.curvature_per_mm == 0.0:
        return g
    radius = 1.0 / abs(g.curvature_per_mm) + d_radius_mm
    angle = g.length_mm * g.curvature_per_mm
    return Segment(radius * abs(angle), math.copysign(1.0 / radius, angle))


def _advance(d: ArrayLike, k: ArrayLike, h0: ArrayLike) -> FloatArray:
    """Chord vector after running d along curvature k from heading h0 (straights: k = 0)."""
    d_, k_, h_ = (np.asarray(a, dtype=np.float64) for a in (d, k, h0))
    half = 0.5 * k_ * d_
    # chord = 2 sin(kd/2)/k = d·sinc(kd/2); numpy's sinc(x) is sin(πx)/(πx); exact at k = 0.
    chord = d_ * np.sinc(half / np.pi)
    ang = h_ + half
    return np.stack([chord * np.cos(ang), chord * np.sin(ang)], axis=-1)


def runway_segments(
    length_mm: float = RUNWAY_LENGTH_MM,
    width_mm: float = RUNWAY_WIDTH_MM,
    radius_mm: float = RUNWAY_CORNER_RADIUS_MM,
) -> list[dict[str, Any]]:
    """Segment dicts of a counter-clockwise rounded rectangle (long straight first)."""
    long_mm, short_mm = length_mm - 2 * radius_mm, width_mm - 2 * radius_mm
    corner = {"kind": "arc", "radius_mm": radius_mm, "angle_deg": 90.0}
    segs: list[dict[str, Any]] = []
    for straight in (long_mm, short_mm, long_mm, short_mm):
        if straight > 0.0:
            segs.append({"kind": "straight", "length_mm": straight})
        segs.append(dict(corner))
    return segs


def runway(height_mm: float = RUNWAY_HEIGHT_MM) -> Track:
    """The paper's runway: 6 m x 3 m, corner radius 1 m, `height_mm` above the floor.

    World origin on the floor below the runway's centre; s = 0 at the start of the long straight
    on the y = -1500 mm side, at x = -2000 mm, travelling +x (counter-clockwise from above).
    """
    half_straight = 0.5 * (RUNWAY_LENGTH_MM - 2 * RUNWAY_CORNER_RADIUS_MM)
    T = make_T(np.eye(3), [-half_straight, -0.5 * RUNWAY_WIDTH_MM, height_mm])
    return Track.from_config(runway_segments(), T, closed=True)
