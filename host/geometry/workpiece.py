"""Workpiece frame from measured feature points (paper §3.1.1) and rangefinder points.

Frame p: origin at P1, Z toward P5, Y in the plane of P1, P3, P5 on P3's side of the Z axis,
X = Y × Z (right-hand rule). Feature points are measured by the rangefinder through the head: it
ranges along the camera's optical axis (+z_c), optionally offset by a fixed T_c_l.
"""

from __future__ import annotations

import numpy as np

from host.geometry.head import Rig
from host.geometry.transforms import ArrayLike, FloatArray, make_T

MIN_BASELINE_MM = 1e-6  # P1-P5 distance below which the Z axis is undefined
MIN_SINE = 1e-9  # sin of the P1-P3 / P1-P5 angle below which the points are collinear
FEATURE_COUNT_MIN = 5  # P1..P5 as in the paper


def workpiece_frame(p1: ArrayLike, p3: ArrayLike, p5: ArrayLike) -> FloatArray:
    """T_w_p from three feature points given in the world frame."""
    a, b, c = (np.asarray(p, dtype=np.float64) for p in (p1, p3, p5))
    z = c - a
    n = float(np.linalg.norm(z))
    if n < MIN_BASELINE_MM:
        raise ValueError("P1 and P5 coincide: the workpiece Z axis is undefined")
    z /= n
    y = (b - a) - np.dot(b - a, z) * z  # Gram-Schmidt: the part of P1→P3 across Z
    m = float(np.linalg.norm(y))
    if m < MIN_SINE * float(np.linalg.norm(b - a)) or m == 0.0:
        raise ValueError("P1, P3 and P5 are collinear: the workpiece Y axis is undefined")
    y /= m
    x = np.cross(y, z)
    return make_T(np.stack([x, y, z], axis=1), a)


def workpiece_frame_from_features(points_w: ArrayLike) -> FloatArray:
    """T_w_p from the paper's feature points P1..Pn (n ≥ 5, rows), using P1, P3 and P5."""
    P = np.asarray(points_w, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < FEATURE_COUNT_MIN:
        raise ValueError(f"need at least {FEATURE_COUNT_MIN} feature points as rows, got {P.shape}")
    return workpiece_frame(P[0], P[2], P[4])


def rangefinder_point(
    rig: Rig,
    s_mm: ArrayLike,
    pan_rad: ArrayLike,
    tilt_rad: ArrayLike,
    range_mm: ArrayLike,
    T_c_l: ArrayLike | None = None,
) -> FloatArray:
    """World point (...,3) hit by a rangefinder reading along +z of frame l (default: camera)."""
    T = rig.T_w_c(s_mm, pan_rad, tilt_rad)
    if T_c_l is not None:
        T = T @ np.asarray(T_c_l, dtype=np.float64)
    r = np.asarray(range_mm, dtype=np.float64)
    out: FloatArray = T[..., :3, 3] + T[..., :3, 2] * r[..., None]
    return out


def measure_workpiece(
    rig: Rig,
    s_mm: ArrayLike,
    pan_rad: ArrayLike,
    tilt_rad: ArrayLike,
    range_mm: ArrayLike,
) -> FloatArray:
    """T_w_p from rangefinder readings of the feature points P1..Pn (arrays of length n)."""
    return workpiece_frame_from_features(rangefinder_point(rig, s_mm, pan_rad, tilt_rad, range_mm))
