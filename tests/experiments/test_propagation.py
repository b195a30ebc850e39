"""§5.1 error propagation: the exact Jacobian, the printed one, and the Monte Carlo check."""

from __future__ import annotations

import numpy as np
import pytest

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

POINT = np.array(PAPER_POINT_MM)


@pytest.mark.parametrize(("a_deg", "b_deg"), [(0, 0), (20, -10), (45, 45)])
def test_exact_jacobian_matches_numeric_derivative(a_deg: float, b_deg: float) -> None:
    a, b, eps = np.deg2rad(a_deg), np.deg2rad(b_deg), 1e-7
    zero = np.zeros(3)
    da = (world_point(POINT, a + eps, b, zero) - world_point(POINT, a - eps, b, zero)) / (2 * eps)
    db = (world_point(POINT, a, b + eps, zero) - world_point(POINT, a, b - eps, zero)) / (2 * eps)
    np.testing.assert_allclose(jacobian_exact(POINT, a, b), np.column_stack([da, db]), atol=1e-4)


def test_printed_eq13_differs_from_the_derivative_at_45_degrees() -> None:
    a = b = np.deg2rad(45)
    printed = np.abs(jacobian_as_printed(POINT, a, b))
    exact = np.abs(jacobian_exact(POINT, a, b))
    assert not np.allclose(printed[2], exact[2], rtol=0.01)  # the ∂Z row carries the slip
    np.testing.assert_allclose(printed[:2], exact[:2])


def test_monte_carlo_agrees_with_first_order_within_5_percent() -> None:
    a = b = np.deg2rad(45)
    sig = Sigmas(5e-4, 5e-4, 0.5)
    first = sigma_first_order(jacobian_exact(POINT, a, b), sig)
    mc = sigma_monte_carlo(POINT, a, b, sig, n=20_000, seed=3)
    np.testing.assert_allclose(mc, first, rtol=0.05)


def test_paper_figures_reproducible_at_zero_angle_but_not_at_45() -> None:
    _, at_zero = fit_paper_sigmas(POINT, 0.0, 0.0)
    np.testing.assert_allclose(at_zero, PAPER_SIGMA_MM, atol=1e-6)
    _, at_45 = fit_paper_sigmas(POINT, np.deg2rad(45), np.deg2rad(45))
    assert np.max(np.abs(at_45 - PAPER_SIGMA_MM)) > 0.1
