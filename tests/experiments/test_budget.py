"""The error budget: first-order overlay σ against a Monte Carlo of the same inputs."""

from __future__ import annotations

import numpy as np
import pytest

from host.experiments.budget import BudgetInputs, monte_carlo, overlay_sigma
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import make_T

WORKPIECE = make_T(np.eye(3), [-300.0, -300.0, 0.0])


def inputs(speed_mm_s: float = 100.0) -> BudgetInputs:
    """A commissioned rig's σ: intrinsics as calibrated, mounts to ~1 mm / 0.3 mrad."""
    cam_sig = np.array([2.0, 2.0, 0.2, 0.3, 0.3, 0.005, 0.13, 0.0, 0.0, 0.0])
    pose = np.diag([3e-4**2] * 3 + [1.0] * 3)
    return BudgetInputs(
        Rig(), CameraModel(), WORKPIECE, np.diag(cam_sig**2), pose, pose, pose,
        sigma_s_mm=0.3, sigma_head_rad=(2e-4, 2e-4), sigma_clock_s=1e-3, speed_mm_s=speed_mm_s,
    )  # fmt: skip


@pytest.mark.parametrize("s_mm", [500.0, 2000.0])
def test_first_order_overlay_sigma_matches_monte_carlo(s_mm: float) -> None:
    rig = Rig()
    points = manipulator_wireframe().vertices
    pan, tilt = rig.aim(s_mm, WORKPIECE[:3, 3] + [0, 0, 300])
    first = overlay_sigma(inputs(), s_mm, pan, tilt, points)
    mc = monte_carlo(inputs(), s_mm, pan, tilt, points, n=400, seed=1)
    assert first.sigma_px == pytest.approx(mc, rel=0.1)
    shares = first.by_source_px
    assert set(shares) == {
        "intrinsics",
        "m_cr",
        "track",
        "workpiece",
        "arc_length",
        "head",
        "arc_radius",
    }
    total_sq = sum(v * v for v in shares.values())
    assert total_sq == pytest.approx(first.sigma_px**2, rel=1e-6)  # independent sources add
    assert first.point_cov.shape[1:] == (2, 2)
    assert 0 < len(first.point_cov) <= len(points)  # the points in view


def test_clock_error_matters_only_when_moving() -> None:
    rig = Rig()
    points = manipulator_wireframe().vertices
    pan, tilt = rig.aim(500.0, WORKPIECE[:3, 3])
    still = overlay_sigma(inputs(0.0), 500.0, pan, tilt, points).by_source_px["arc_length"]
    fast = overlay_sigma(inputs(2000.0), 500.0, pan, tilt, points).by_source_px["arc_length"]
    # σ_s grows from 0.3 mm to sqrt(0.3² + 2²) mm: the pixel share by the same factor
    assert fast / still == pytest.approx(np.hypot(0.3, 2.0) / 0.3, rel=1e-3)
