"""View plans: where to put the trolley and the head so a fixed board covers what a fit needs.

The installer gives the board's rough pose in the world (a tape measure is enough: the plan
only aims the head). From the nominal rig and camera, each station along the track gets head
angles that put the board's centre at chosen places in the image (centre and four corners), so
the views spread the board over the image; stations at different distances along the track
vary its size and its tilt to the optical axis. The aiming is Newton's method on the board
centre's pixel, two angles for two coordinates, started from `Rig.aim`. A pan/tilt head reaches
most directions two ways (pan + π with the tilt mirrored): a view whose first solution lies
outside the head's limits is aimed the other way, and a pan is taken modulo 2π into them, so a
head whose tilt only turns one way (or whose pan stops short of ±π) still gets its views. Where
both ways fit, a board view takes the first (`board_plan` says why); a view of the workpiece's
targets takes the one nearer the view before it (`aim_within` with `near`): the head slews at
about 1 rad/s, and the other way round can be a turn of π.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray, transform_points

AIM_STEPS = 8
AIM_TOL_PX = 0.5
DIFF_RAD = 1e-5
# Where the board's centre goes, as fractions of the image (centre first: the easiest view).
IMAGE_TARGETS = ((0.5, 0.5), (0.3, 0.3), (0.7, 0.3), (0.3, 0.7), (0.7, 0.7))


@dataclass(frozen=True)
class ViewTarget:
    """One planned view: trolley arc length, head angles, and a label for the report."""

    s_mm: float
    pan_rad: float
    tilt_rad: float
    label: str

    def as_dict(self) -> dict[str, float | str]:
        """Plain values."""
        return {
            "s_mm": self.s_mm,
            "pan_rad": self.pan_rad,
            "tilt_rad": self.tilt_rad,
            "label": self.label,
        }


def aim_at_pixel(
    rig: Rig, camera: CameraModel, s_mm: float, point_w: FloatArray, target_uv: FloatArray,
    start: tuple[float, float] | None = None,
) -> tuple[float, float] | None:  # fmt: skip
    """Head angles putting a world point at a pixel (nominal rig); None if it cannot be done.

    Newton from `start` (default `Rig.aim`, the smaller head excursion)."""
    pan, tilt = rig.aim(s_mm, point_w) if start is None else start
    for _ in range(AIM_STEPS):
        uv = _pixel(rig, camera, s_mm, pan, tilt, point_w)
        if uv is None:
            return None
        err = uv - target_uv
        if float(np.hypot(*err)) < AIM_TOL_PX:
            return pan, tilt
        du_pan = _pixel(rig, camera, s_mm, pan + DIFF_RAD, tilt, point_w)
        du_tilt = _pixel(rig, camera, s_mm, pan, tilt + DIFF_RAD, point_w)
        if du_pan is None or du_tilt is None:
            return None
        J = np.column_stack([(du_pan - uv) / DIFF_RAD, (du_tilt - uv) / DIFF_RAD])
        try:
            step = np.linalg.solve(J, -err)
        except np.linalg.LinAlgError:
            return None
        pan, tilt = pan + float(step[0]), tilt + float(step[1])
    final = _pixel(rig, camera, s_mm, pan, tilt, point_w)
    ok = final is not None and float(np.hypot(*(final - target_uv))) < 10 * AIM_TOL_PX
    return (pan, tilt) if ok else None


def board_plan(
    rig: Rig,
    camera: CameraModel,
    board_centre_w: FloatArray,
    stations_mm: Sequence[float],
    targets: Sequence[tuple[float, float]] = IMAGE_TARGETS,
    limits: tuple[tuple[float, float], tuple[float, float]] | None = None,
) -> list[ViewTarget]:
    """Views of the board from each station at each image target, within the head's limits.

    Each view takes `Rig.aim`'s way where it fits, not the one nearer the view before: that
    turns the head further, but the views then tilt both ways (the stations before and after
    the board see it on either side of the tilt's zero), and the head calibration needs both.
    Planned the nearer way, all tilted one way, the acceptance check's RMS rose from ~0.05 to
    0.33 px (seed 2)."""
    plan = []
    size = np.array([camera.width - 1.0, camera.height - 1.0])
    for s in stations_mm:
        for fx, fy in targets:
            angles = aim_within(rig, camera, s, board_centre_w, size * np.array([fx, fy]), limits)
            if angles is None:
                continue
            plan.append(
                ViewTarget(float(s), angles[0], angles[1], f"s={s:.0f} at ({fx:.1f}, {fy:.1f})")
            )
    return plan


def aim_within(
    rig: Rig, camera: CameraModel, s_mm: float, point_w: FloatArray, target_uv: FloatArray,
    limits: tuple[tuple[float, float], tuple[float, float]] | None,
    near: tuple[float, float] | None = None,
) -> tuple[float, float] | None:  # fmt: skip
    """`aim_at_pixel` within the head's limits: either way of reaching the direction, the pan
    taken modulo 2π; the first way that fits, or with `near` the one the head reaches soonest
    from there; None when neither fits."""
    options = aim_options(rig, camera, s_mm, point_w, target_uv, limits)
    if not options or near is None:
        return options[0] if options else None
    return min(options, key=lambda a: slew_rad(near, a))


def aim_options(
    rig: Rig, camera: CameraModel, s_mm: float, point_w: FloatArray, target_uv: FloatArray,
    limits: tuple[tuple[float, float], tuple[float, float]] | None,
) -> list[tuple[float, float]]:  # fmt: skip
    """Both ways of putting a world point at a pixel that lie within the limits (`Rig.aim`'s
    first, the smaller head excursion)."""
    first = rig.aim(s_mm, point_w)
    out = []
    for start in (first, other_way(rig, first)):
        angles = aim_at_pixel(rig, camera, s_mm, point_w, target_uv, start)
        if angles is None:
            continue
        angles = wrap_pan(angles, limits)
        if within_limits(angles, limits):
            out.append(angles)
    return out


def slew_rad(a: tuple[float, float], b: tuple[float, float]) -> float:
    """How far the head turns from a to b: both axes slew at once, the larger angle counts."""
    return max(abs(a[0] - b[0]), abs(a[1] - b[1]))


def other_way(rig: Rig, angles: tuple[float, float]) -> tuple[float, float]:
    """The head's second way to the same optical axis: pan + π, the tilt mirrored about the
    tilt that brings the camera's axis onto the pan axis (`Rig.aim`'s two branches)."""
    axis = rig.T_r_c[:3, 2]
    base = math.atan2(-float(axis[0]), float(axis[2]))
    return math.remainder(angles[0] + math.pi, math.tau), 2.0 * base - angles[1]


def wrap_pan(
    angles: tuple[float, float], limits: tuple[tuple[float, float], tuple[float, float]] | None
) -> tuple[float, float]:
    """The same pan ± 2π when that is what lies within the limits (a head that turns past ±π)."""
    if limits is None:
        return angles
    (p0, p1), _ = limits
    pan = angles[0]
    for turn in (0.0, math.tau, -math.tau):
        if p0 <= pan + turn <= p1:
            return pan + turn, angles[1]
    return angles


def sweep(stations_mm: Sequence[float], s_now_mm: float | None) -> list[float]:
    """The stations in one sweep along the track from the end nearer the trolley (the order
    does not change what a fit sees, only how far the trolley runs)."""
    ordered = sorted(stations_mm)
    if s_now_mm is not None and abs(ordered[-1] - s_now_mm) < abs(ordered[0] - s_now_mm):
        ordered.reverse()
    return ordered


def within_limits(
    angles: tuple[float, float], limits: tuple[tuple[float, float], tuple[float, float]] | None
) -> bool:
    """Inside the head's (pan, tilt) limits."""
    if limits is None:
        return True
    (p0, p1), (t0, t1) = limits
    return p0 <= angles[0] <= p1 and t0 <= angles[1] <= t1


def _pixel(
    rig: Rig, camera: CameraModel, s_mm: float, pan: float, tilt: float, point_w: FloatArray
) -> FloatArray | None:
    """Where the nominal rig sees a world point, None behind the camera."""
    pc = transform_points(rig.T_c_w(s_mm, pan, tilt), np.asarray(point_w, dtype=np.float64))
    uv, valid = camera.project(pc)
    return uv if bool(valid) else None
