"""Error propagation of the paper's §5.1 (eq. 10–13): first order, as printed, and Monte Carlo.

The paper maps a camera-frame point through the head rotation Ry(β)·Rx(α) plus the track
translation (eq. 10/11, M_cr = I) and propagates independent σ of α, β and t to σ of the world
coordinates (eq. 13). Its printed partial derivatives (eq. 12) carry sign slips: ∂Z/∂α is printed
with −sin α cos β Z in eq. 12 but +sin α cos β Z in eq. 13, while differentiating eq. 11 gives
cos α cos β Y − sin α cos β Z. We compute the Jacobian of eq. 11 exactly, also evaluate eq. 13 as
printed, and check the exact one against a Monte Carlo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

PAPER_SIGMA_MM = (1.51, 1.55, 1.13)  # σX, σY, σZ as printed in §5.1
PAPER_POINT_MM = (100.0, 100.0, 3000.0)  # X = Y = 100 mm, Z = 3000 mm
PAPER_MAX_ANGLE_RAD = np.deg2rad(45.0)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Sigmas:
    """Input standard deviations: head angles in radians, track translation in mm."""

    alpha_rad: float
    beta_rad: float
    t_mm: float


def world_point(
    point_c: FloatArray, alpha: FloatArray, beta: FloatArray, t: FloatArray
) -> FloatArray:
    """Eq. 11: world coordinates of a camera-frame point; angles and t broadcast (…, 3)."""
    x, y, z = point_c
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
    xw = cb * x + sa * sb * y + ca * sb * z
    yw = ca * y - sa * z
    zw = -sb * x + sa * cb * y + ca * cb * z
    return np.stack([xw, yw, zw], axis=-1) + t


def jacobian_exact(point_c: FloatArray, alpha: float, beta: float) -> FloatArray:
    """∂(Xw, Yw, Zw)/∂(α, β): the derivative of eq. 11 (3×2)."""
    x, y, z = point_c
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
    return np.array(
        [
            [ca * sb * y - sa * sb * z, -sb * x + sa * cb * y + ca * cb * z],
            [-sa * y - ca * z, 0.0],
            [ca * cb * y - sa * cb * z, -cb * x - sa * sb * y - ca * sb * z],
        ]
    )


def jacobian_as_printed(point_c: FloatArray, alpha: float, beta: float) -> FloatArray:
    """The coefficients exactly as eq. 13 prints them (3×2)."""
    x, y, z = point_c
    ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
    return np.array(
        [
            [ca * sb * y - sa * sb * z, sb * x - sa * cb * y - ca * cb * z],
            [sa * y + ca * z, 0.0],
            [ca * cb * y + sa * cb * z, -cb * x + sa * sb * y + ca * sb * z],
        ]
    )


def sigma_first_order(jac: FloatArray, sig: Sigmas) -> FloatArray:
    """Eq. 13's form: σ of each world coordinate from independent inputs."""
    angle_var = jac[:, 0] ** 2 * sig.alpha_rad**2 + jac[:, 1] ** 2 * sig.beta_rad**2
    return np.asarray(np.sqrt(angle_var + sig.t_mm**2), dtype=np.float64)


def sigma_monte_carlo(
    point_c: FloatArray, alpha: float, beta: float, sig: Sigmas, n: int, seed: int
) -> FloatArray:
    """σ of the world coordinates by sampling the inputs (n samples, seeded)."""
    rng = np.random.default_rng(seed)
    da = rng.normal(0.0, sig.alpha_rad, n)
    db = rng.normal(0.0, sig.beta_rad, n)
    dt = rng.normal(0.0, sig.t_mm, (n, 3))
    pts = world_point(point_c, alpha + da, beta + db, dt)
    return np.asarray(pts.std(axis=0, ddof=1), dtype=np.float64)


def worst_case_over_angles(
    point_c: FloatArray, sig: Sigmas, max_angle: float, printed: bool, steps: int = 46
) -> tuple[FloatArray, tuple[float, float]]:
    """Largest σ per coordinate over the (α, β) grid up to max_angle, and where σX peaks."""
    grid = np.linspace(0.0, max_angle, steps)
    jac_fn = jacobian_as_printed if printed else jacobian_exact
    best = np.zeros(3)
    where = (0.0, 0.0)
    for a in grid:
        for b in grid:
            s = sigma_first_order(jac_fn(point_c, float(a), float(b)), sig)
            if s[0] > best[0]:
                where = (float(a), float(b))
            best = np.maximum(best, s)
    return best, where


def fit_paper_sigmas(point_c: FloatArray, alpha: float, beta: float) -> tuple[Sigmas, FloatArray]:
    """Input σ (non-negative) that best reproduce the paper's printed σ at one setting.

    Squared σ are linear in the input variances, so this is a small non-negative least squares
    solved by enumerating active sets; the residual shows whether any inputs can produce them.
    """
    jac = jacobian_as_printed(point_c, alpha, beta)
    a = np.column_stack([jac[:, 0] ** 2, jac[:, 1] ** 2, np.ones(3)])
    target = np.square(np.asarray(PAPER_SIGMA_MM))
    best: tuple[float, FloatArray] = (np.inf, np.zeros(3))
    for mask in range(1, 8):
        cols = [i for i in range(3) if mask >> i & 1]
        sol, *_ = np.linalg.lstsq(a[:, cols], target, rcond=None)
        if np.any(sol < 0):
            continue
        var = np.zeros(3)
        var[cols] = sol
        err = float(np.linalg.norm(a @ var - target))
        if err < best[0]:
            best = (err, var)
    var = best[1]
    sig = Sigmas(float(np.sqrt(var[0])), float(np.sqrt(var[1])), float(np.sqrt(var[2])))
    reproduced = np.sqrt(a @ var)
    return sig, np.asarray(reproduced, dtype=np.float64)
