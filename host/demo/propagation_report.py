"""§5.1 for the report: σ of world coordinates and of pixels, first order and Monte Carlo."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from host.experiments.propagation import (
    PAPER_POINT_MM,
    PAPER_SIGMA_MM,
    Sigmas,
    fit_paper_sigmas,
    jacobian_as_printed,
    jacobian_exact,
    sigma_first_order,
    sigma_monte_carlo,
    world_point,
)
from host.geometry.camera import CameraModel

FloatArray = NDArray[np.float64]
ANGLES_DEG = (0.0, 15.0, 30.0, 45.0)


def pixel_sigma(
    camera: CameraModel,
    point_c: FloatArray,
    alpha: float,
    beta: float,
    sig: Sigmas,
    n: int,
    seed: int,
) -> tuple[FloatArray, FloatArray]:
    """σ(u, v) of a world point re-projected through a perturbed head: (first order, MC)."""
    rng = np.random.default_rng(seed)
    zero = np.zeros(3)
    p_w = world_point(point_c, np.array(alpha), np.array(beta), zero)

    def uv(da: FloatArray, db: FloatArray, dt: FloatArray) -> FloatArray:
        # The world point as the perturbed head believes the camera sees it (M_cr = I, eq. 10).
        a, b = alpha + da, beta + db
        ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
        d = p_w - dt
        x = cb * d[..., 0] - sb * d[..., 2]
        y = sa * sb * d[..., 0] + ca * d[..., 1] + sa * cb * d[..., 2]
        z = ca * sb * d[..., 0] - sa * d[..., 1] + ca * cb * d[..., 2]
        pts = np.stack([x, y, z], axis=-1)
        out, _ = camera.project(pts.reshape(-1, 3))
        return out.reshape(*np.shape(x), 2)

    eps = 1e-6
    base = uv(np.zeros(1), np.zeros(1), zero[None, :])[0]
    cols = [
        (uv(np.array([eps]), np.zeros(1), zero[None, :])[0] - base) / eps * sig.alpha_rad,
        (uv(np.zeros(1), np.array([eps]), zero[None, :])[0] - base) / eps * sig.beta_rad,
    ]
    for k in range(3):
        dt = np.zeros((1, 3))
        dt[0, k] = 1e-3
        cols.append((uv(np.zeros(1), np.zeros(1), dt)[0] - base) / 1e-3 * sig.t_mm)
    first = np.sqrt(np.sum(np.square(cols), axis=0))
    da = rng.normal(0.0, sig.alpha_rad, n)
    db = rng.normal(0.0, sig.beta_rad, n)
    dt = rng.normal(0.0, sig.t_mm, (n, 3))
    mc = uv(da, db, dt).std(axis=0, ddof=1)
    return np.asarray(first, dtype=np.float64), np.asarray(mc, dtype=np.float64)


def propagation_results(camera: CameraModel, samples: int) -> dict[str, Any]:
    """Every §5.1 figure for the report and results.json."""
    point = np.array(PAPER_POINT_MM)
    sig, reproduced = fit_paper_sigmas(point, 0.0, 0.0)
    rows = []
    for deg in ANGLES_DEG:
        a = b = float(np.deg2rad(deg))
        exact = sigma_first_order(jacobian_exact(point, a, b), sig)
        printed = sigma_first_order(jacobian_as_printed(point, a, b), sig)
        mc = sigma_monte_carlo(point, a, b, sig, samples, seed=int(deg) + 1)
        px_first, px_mc = pixel_sigma(camera, point, a, b, sig, samples, seed=int(deg) + 101)
        rows.append(
            {
                "angle_deg": deg,
                "first_order_mm": exact.tolist(),
                "as_printed_mm": printed.tolist(),
                "monte_carlo_mm": mc.tolist(),
                "mc_agreement": float(np.max(np.abs(mc / exact - 1.0))),
                "pixel_first_order": px_first.tolist(),
                "pixel_monte_carlo": px_mc.tolist(),
            }
        )
    _, at45 = fit_paper_sigmas(point, float(np.deg2rad(45)), float(np.deg2rad(45)))
    return {
        "paper_sigma_mm": list(PAPER_SIGMA_MM),
        "input_sigma": {"alpha_rad": sig.alpha_rad, "beta_rad": sig.beta_rad, "t_mm": sig.t_mm},
        "reproduced_at_0deg_mm": reproduced.tolist(),
        "best_fit_at_45deg_mm": at45.tolist(),
        "samples": samples,
        "rows": rows,
    }
