"""Levenberg-Marquardt for the calibrations, and the parameter covariance it implies.

One solver for every calibration here (intrinsics with skew, hand-eye, the error budget's
checks): Marquardt's damping by diag(JᵀJ), so parameters in px, mm and rad need no scaling. The
covariance of the estimate is (JᵀJ)⁻¹ scaled by the residual variance rᵀr / (m − n), the usual
first-order result for independent pixel noise of equal σ; `sigma` is its diagonal's root.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from host.geometry.transforms import FloatArray

ResidualFn = Callable[[FloatArray], FloatArray]
JacobianFn = Callable[[FloatArray, FloatArray], FloatArray]  # (x, r(x)) → J

LAMBDA0 = 1e-3
MAX_ITERATIONS = 60
REL_TOL = 1e-12  # relative cost decrease at which the solver stops
LAMBDA_MAX = 1e12


@dataclass(frozen=True)
class Solution:
    """The estimate, its residuals and Jacobian there, and the covariance."""

    x: FloatArray
    residuals: FloatArray
    jacobian: FloatArray
    covariance: FloatArray
    iterations: int

    @property
    def sigma(self) -> FloatArray:
        """One-sigma uncertainty of each parameter."""
        out: FloatArray = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return out

    @property
    def residual_variance(self) -> float:
        """rᵀr / (m − n): the per-residual noise variance the fit implies."""
        return residual_variance(self.residuals, self.x.size)


def residual_variance(r: FloatArray, n_params: int) -> float:
    """Unbiased variance of the residuals of an n-parameter fit."""
    dof = max(r.size - n_params, 1)
    return float(r @ r) / dof


def covariance(J: FloatArray, r: FloatArray) -> FloatArray:
    """(JᵀJ)⁻¹ · rᵀr/(m − n); a pseudo-inverse keeps an unobservable direction finite."""
    H = J.T @ J
    inv = np.linalg.pinv(H, rcond=1e-14, hermitian=True)
    out: FloatArray = np.asarray(inv * residual_variance(r, J.shape[1]), dtype=np.float64)
    return out


def forward_jacobian(fn: ResidualFn, steps: FloatArray) -> JacobianFn:
    """A Jacobian by forward differences with one step per parameter."""

    def jac(x: FloatArray, r0: FloatArray) -> FloatArray:
        J = np.empty((r0.size, x.size))
        for j in range(x.size):
            xj = x.copy()
            xj[j] += steps[j]
            J[:, j] = (fn(xj) - r0) / steps[j]
        return J

    return jac


def solve(fn: ResidualFn, x0: FloatArray, jac: JacobianFn) -> Solution:
    """Minimise |fn(x)|² from x0; returns the estimate with its covariance."""
    x = np.asarray(x0, dtype=np.float64).copy()
    r = fn(x)
    cost, lam = float(r @ r), LAMBDA0
    J = jac(x, r)
    it = 0
    while it < MAX_ITERATIONS:
        it += 1
        H, g = J.T @ J, J.T @ r
        damped = H + lam * np.diag(np.maximum(np.diag(H), 1e-12))
        try:
            step = np.linalg.solve(damped, -g)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(damped, -g, rcond=None)[0]
        x_new = x + step
        r_new = fn(x_new)
        c_new = float(r_new @ r_new)
        if c_new < cost:
            done = cost - c_new <= REL_TOL * cost
            x, r, cost, lam = x_new, r_new, c_new, max(lam * 0.3, 1e-12)
            J = jac(x, r)
            if done:
                break
        else:
            lam *= 10.0
            if lam > LAMBDA_MAX:
                break
    return Solution(x, r, J, covariance(J, r), it)
