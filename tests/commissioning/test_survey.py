"""The workpiece frame from surveyed points: the paper's 3-point frame, the LS fit, honest σ."""

from __future__ import annotations

import numpy as np
import pytest

from host.commissioning.survey import fit_frame, frame_from_three
from host.geometry.transforms import R_to_rotvec, euler_zyx, make_T, transform_points

MODEL_P = np.array([[0, 0, 0], [400, 0, 200], [0, 300, 600], [-200, 250, 900], [0, 0, 1200]], float)
TRUE_T = make_T(euler_zyx(0.3, -0.1, 0.05), [-300.0, -300.0, 20.0])


def local_error(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    d = np.linalg.inv(est) @ truth
    return np.concatenate([R_to_rotvec(d[:3, :3]), d[:3, 3]])


def z_scores(fits: list, truth: np.ndarray) -> np.ndarray:  # type: ignore[type-arg]
    """Each fit's error in units of its reported σ, per local axis."""
    return np.array([local_error(f.T_w_p, truth) / np.sqrt(np.diag(f.covariance)) for f in fits])


def test_least_squares_frame_reports_the_sigma_it_achieves() -> None:
    rng = np.random.default_rng(0)
    measured = transform_points(TRUE_T, MODEL_P)
    fits = [
        fit_frame(measured + rng.normal(0, 1.0, measured.shape), MODEL_P, 1.0) for _ in range(300)
    ]
    z = z_scores(fits, TRUE_T)
    assert np.all(np.abs(z.std(axis=0) - 1.0) < 0.15), z.std(axis=0)  # σ neither over nor under
    assert fits[0].residuals_mm.shape == (5,)
    assert 0.3 < fits[0].rms_mm < 2.0


def test_three_point_frame_is_the_papers_and_its_sigma_holds() -> None:
    rng = np.random.default_rng(1)
    p = transform_points(TRUE_T, MODEL_P)
    exact = frame_from_three(p[0], p[2], p[4], 1.0).T_w_p
    assert exact[:3, 3] == pytest.approx(p[0])  # origin at P1
    z_axis = (p[4] - p[0]) / np.linalg.norm(p[4] - p[0])
    assert exact[:3, 2] == pytest.approx(z_axis)  # Z along P1 → P5
    fits = []
    for _ in range(300):
        q = p[[0, 2, 4]] + rng.normal(0, 1.0, (3, 3))
        fits.append(frame_from_three(q[0], q[1], q[2], 1.0))
    z = z_scores(fits, exact)
    assert np.all(np.abs(z.std(axis=0) - 1.0) < 0.15), z.std(axis=0)


def test_too_few_or_collinear_points_are_refused() -> None:
    with pytest.raises(ValueError, match="need ≥ 3"):
        fit_frame(MODEL_P[:2], MODEL_P[:2], 1.0)
    line = np.array([[0, 0, 0], [0, 0, 100], [0, 0, 200]], float)
    with pytest.raises(ValueError, match="collinear"):
        fit_frame(line, line, 1.0)
