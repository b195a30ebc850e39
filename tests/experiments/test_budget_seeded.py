"""The error budget against seeded rigs commissioned with the real solvers (slow: ~2 min).

Predicted σ (each rig's own file) beside the measured spread of the overlay error across the
rigs, at the demo's observation points and on the far side of the loop; issue 11's target is
±30 %. With six rigs the measured σ is itself uncertain by ~±12 % (68 %): the bench
(benchmarks/bench_budget.py) runs more.
"""

from __future__ import annotations

import numpy as np
import pytest

from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import FloatArray
from host.rig.schema import HEAD_ANGLE_SIGMA_RAD
from tests.experiments.seeded_rigs import (
    Commissioned,
    board_relative_workpiece,
    camera_surveyed_workpiece,
    commission,
    joint_nees,
    predicted_and_measured,
)

SEEDS = range(1, 7)
OFFSETS_MM = (0.0, 2000.0, 7000.0)


@pytest.fixture(scope="module")
def rigs() -> list[Commissioned]:
    return [commission(seed) for seed in SEEDS]


def _ratios(meas: FloatArray, pred: FloatArray) -> FloatArray:
    out: FloatArray = np.sqrt(np.nanmean(pred, axis=0) / np.nanmean(meas, axis=0))
    return out


@pytest.mark.slow
def test_predicted_overlay_sigma_within_30_percent_of_measured(rigs: list[Commissioned]) -> None:
    for c in rigs:  # what calibrate head wrote: the joint block over all four, read back
        assert c.host.covariance is not None
        names = {"head.m_cr", "track.placement", "camera.intrinsics", "track.home"}
        assert set(c.host.covariance.names) == names
    points = manipulator_wireframe().vertices
    meas, pred = predicted_and_measured(rigs, OFFSETS_MM, points)
    assert np.isfinite(meas).all()
    ratio = _ratios(meas, pred)
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio


@pytest.mark.slow
def test_the_joint_covariance_is_consistent_with_the_errors(rigs: list[Commissioned]) -> None:
    """NEES of intrinsics, M_cr and placement against the truth: its mean is the dof (19)
    when the joint covariance is right (χ²: with six rigs the mean is within ±30 % of it at
    ~2σ). Before the hand-eye counted the head angles' noise it was ~100."""
    values = [joint_nees(c) for c in rigs]
    dof = values[0][1]
    mean = float(np.mean([v for v, _ in values]))
    assert 0.7 * dof < mean < 1.5 * dof, (mean, dof)


@pytest.mark.slow
def test_shared_survey_error_cancels_as_the_cross_terms_say(rigs: list[Commissioned]) -> None:
    """The workpiece surveyed in the board's frame: without the cross terms the budget counts
    the board survey's error twice and over-predicts; with them it is within ±30 %."""
    rel = [board_relative_workpiece(c, np.random.default_rng([c.seed, 11])) for c in rigs]
    points = manipulator_wireframe().vertices
    meas, pred = predicted_and_measured(rel, OFFSETS_MM[:2], points)
    _, plain = predicted_and_measured(rel, OFFSETS_MM[:2], points, without_cross=True)
    with_cross, without = _ratios(meas, pred), _ratios(meas, plain)
    assert np.all((with_cross > 0.7) & (with_cross < 1.3)), with_cross
    assert np.all(without > 1.3), without


@pytest.mark.slow
def test_a_camera_surveyed_workpiece_is_predicted_within_30_percent(
    rigs: list[Commissioned],
) -> None:
    """The workpiece surveyed by the camera through the commissioned rig, as the demo does: it
    carries the rig's errors along, and near the survey most of them cancel in the overlay. The
    budget sees that through the frame's dependence on every block (within ±30 %); without the
    cross terms it counts the rig's error twice over."""
    surveyed = [camera_surveyed_workpiece(c) for c in rigs]
    points = manipulator_wireframe().vertices
    meas, pred = predicted_and_measured(surveyed, OFFSETS_MM[:2], points)
    _, plain = predicted_and_measured(surveyed, OFFSETS_MM[:2], points, without_cross=True)
    with_cross, without = _ratios(meas, pred), _ratios(meas, plain)
    assert np.all((with_cross > 0.7) & (with_cross < 1.3)), with_cross
    assert np.all(without > 2.0), without


@pytest.mark.slow
def test_the_datasheet_head_noise_over_predicts_a_head_that_reads_at_rest(
    rigs: list[Commissioned],
) -> None:
    """The head stands on a count and reads it (the simulator's plant): its read noise, as
    measured at the rests, is a fraction of the datasheet's, and a rig file that kept the
    datasheet's over-predicted the demo's static overlay (issue 11: 2-6× on seeds 1-3). The
    same rigs with the datasheet's σ: the budget is beyond +30 % at the demo's observation
    points; with the measured σ within ±30 % (the test above)."""
    for c in rigs:
        noise = c.host.head.angle_noise
        assert noise.provenance.method.startswith("measured at rest")
        assert 0.0 < noise.sigma < 0.6 * HEAD_ANGLE_SIGMA_RAD
    datasheet = [camera_surveyed_workpiece(commission(c.seed, measure_head=False)) for c in rigs]
    points = manipulator_wireframe().vertices
    meas, pred = predicted_and_measured(datasheet, OFFSETS_MM[:2], points)
    assert np.all(_ratios(meas, pred) > 1.3), _ratios(meas, pred)
