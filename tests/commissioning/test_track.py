"""`survey track`: the first corner's place and the arcs' radius from readings through the corner.

The truth is drawn from the σ the rig file states (mount, placement, walls; tests'
rangefinder_truth) with the first corner off along the track (a zero off and the placement off
the other way, as the commissioning on the first straight leaves them) and every arc bent to
another radius; readings come from `range_at` on the true rig.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from host.commissioning import track_run
from host.commissioning.client import run_op
from host.commissioning.range_model import corner_shift
from host.geometry.transforms import make_T
from host.rig import (
    JointCovariance,
    RigSpec,
    build_kinematics,
    dumps_rig,
    load_rig,
    loads_rig,
    with_updates,
)
from tests.commissioning.rangefinder_truth import Truth, draw_truth, hall_rig, sensed_daemon
from tests.commissioning.test_rangefinder import SAMPLES, readings

HOME_MM = 150.0


def cornered_truth(spec: RigSpec, rng: np.random.Generator) -> tuple[Truth, float, float]:
    """A true rig whose first corner is δ along the track from the host's and whose arcs are
    bent dR wider; (truth, δ, dR)."""
    t = draw_truth(spec, rng, mount_from_spec=True, shift_sigma_mm=0.0)
    delta, dr = float(rng.normal(0.0, 6.0)), float(rng.normal(0.0, 2.0))
    rig = dataclasses.replace(t.rig, track=t.rig.track.with_arc_radius_change(dr))
    return Truth(corner_shift(rig, delta), t.scene, delta, t.marks_mm), delta, dr


def views_for(spec: RigSpec, stations: list[float] | None = None) -> list:  # type: ignore[type-arg]
    views = track_run.plan(spec, stations, 8, (spec.head.tilt_min_rad, spec.head.tilt_max_rad))
    assert not isinstance(views, str), views
    return views


def test_the_corner_and_the_radius_are_recovered_within_the_sigma_they_report() -> None:
    spec = hall_rig()
    views = views_for(spec)
    z = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        truth, delta, dr = cornered_truth(spec, rng)
        fit = track_run.fit_track(spec, readings(spec, truth, rng, views))
        assert fit.passed, fit.reasons
        assert fit.radius_fitted
        z.append(((fit.corner_mm - delta) / fit.corner_sigma_mm,
                  (fit.radius_change_mm - dr) / fit.radius_sigma_mm))  # fmt: skip
    assert np.all(np.abs(z) < 3.0), z


def test_the_update_keeps_the_first_straights_poses_and_moves_the_corner() -> None:
    spec = hall_rig()
    rng = np.random.default_rng(7)
    truth, delta, _ = cornered_truth(spec, rng)
    fit = track_run.fit_track(spec, readings(spec, truth, rng, views_for(spec)))
    assert fit.passed, fit.reasons
    new = with_updates(spec, track_run.track_update(spec, fit, SAMPLES))
    new = loads_rig(dumps_rig(new))  # round-trips, joint covariance and all
    assert new.track.home.value == pytest.approx(spec.track.home.value + fit.corner_mm)
    assert new.track.home.provenance.method.startswith("survey track")
    assert new.track.arcs.method.startswith("survey track")
    assert new.track.arc_radius_sigma_mm == pytest.approx(fit.radius_sigma_mm)
    arcs = [s.radius_mm for s in new.track.segments if s.kind == "arc"]
    assert arcs == pytest.approx([1000.0 + fit.radius_change_mm] * 4)
    old_rig, new_rig = build_kinematics(spec), build_kinematics(new)
    shift = new.track.home.value - spec.track.home.value
    for p in (0.0, 1000.0, 3500.0):  # controller positions on the first straight
        s = p + spec.track.home.value
        assert np.allclose(new_rig.track.pose(s + shift), old_rig.track.pose(s), atol=1e-6)
    s_arc = 4000.0 + 700.0 - spec.track.home.value  # a controller position in the first arc
    true_pos = truth.rig.track.pose(s_arc + spec.track.home.value + delta)[:3, 3]
    got = new_rig.track.pose(s_arc + new.track.home.value)[:3, 3]
    was = old_rig.track.pose(s_arc + spec.track.home.value)[:3, 3]
    # the placement's own errors stay (the fit does not write them): the arc is as near the
    # truth as the straight, much nearer than before
    straight_err = np.linalg.norm(
        old_rig.track.pose(2000.0)[:3, 3] - truth.rig.track.pose(2000.0 + delta)[:3, 3]
    )
    assert np.linalg.norm(got - true_pos) < straight_err + 3.0
    assert np.linalg.norm(got - true_pos) < np.linalg.norm(was - true_pos) or abs(delta) < 2.0


def test_the_update_carries_a_joint_covariance_through() -> None:
    spec = hall_rig()
    # calibrate head leaves the zero and the placement's x anti-correlated (only their sum seen)
    cov = np.zeros((7, 7))
    cov[:6, :6] = spec.track.placement.cov()
    cov[6, 6] = 25.0
    cov[3, 6] = cov[6, 3] = -0.98 * 5.0 * 5.0
    home = dataclasses.replace(spec.track.home, sigma=5.0)
    spec = dataclasses.replace(
        spec,
        track=dataclasses.replace(spec.track, home=home),
        covariance=JointCovariance(("track.placement", "track.home"), cov),
    )
    rng = np.random.default_rng(3)
    truth, _, _ = cornered_truth(spec, rng)
    fit = track_run.fit_track(spec, readings(spec, truth, rng, views_for(spec)))
    assert fit.passed, fit.reasons
    new = loads_rig(dumps_rig(with_updates(spec, track_run.track_update(spec, fit, SAMPLES))))
    assert new.covariance is not None
    assert new.track.home.sigma == pytest.approx(fit.corner_sigma_mm)
    # the sum (zero + placement x), which the straight fixed, keeps its σ
    before = 25.0 + 25.0 + 2 * cov[3, 6]
    m, at = new.covariance.matrix, new.covariance.slices()
    tx, h = at["track.placement"].start + 3, at["track.home"].start
    after = m[tx, tx] + m[h, h] + 2 * m[tx, h]
    assert after == pytest.approx(before, rel=1e-6)


def test_too_few_readings_or_none_past_the_corner_fail_and_write_nothing() -> None:
    spec = hall_rig()
    rng = np.random.default_rng(11)
    truth, _, _ = cornered_truth(spec, rng)
    few = readings(spec, truth, rng, views_for(spec)[:5])
    fit = track_run.fit_track(spec, few)
    assert not fit.passed
    assert "distinct poses" in fit.reasons[0]
    with pytest.raises(ValueError, match="only a passing survey"):
        track_run.track_update(spec, fit, SAMPLES)
    straight = readings(spec, truth, rng, views_for(spec, [1500.0, 2500.0, 3500.0]))
    fit = track_run.fit_track(spec, straight)
    assert not fit.passed
    assert "past the first corner" in fit.reasons[0]


def test_an_open_track_fits_the_corner_only() -> None:
    base = hall_rig()
    segs = base.track.segments[:3]  # straight, arc, straight: an open L
    track = dataclasses.replace(base.track, segments=segs, closed=False, travel_min_mm=0.0,
                                travel_max_mm=sum(s.arc_length_mm for s in segs))  # fmt: skip
    spec = dataclasses.replace(base, track=track)
    rng = np.random.default_rng(5)
    t = draw_truth(spec, rng, mount_from_spec=True, shift_sigma_mm=0.0)
    truth = Truth(corner_shift(t.rig, 4.0), t.scene, 4.0, t.marks_mm)
    fit = track_run.fit_track(spec, readings(spec, truth, rng, views_for(spec)))
    assert fit.passed, fit.reasons
    assert not fit.radius_fitted
    assert abs(fit.corner_mm - 4.0) < 3 * fit.corner_sigma_mm
    updates = track_run.track_update(spec, fit, SAMPLES)
    assert "track.segments" not in updates


def test_a_track_without_a_first_corner_is_refused() -> None:
    base = hall_rig()
    track = dataclasses.replace(base.track, segments=base.track.segments[1:2], closed=False)
    spec = dataclasses.replace(base, track=track)
    assert "no first corner" in str(track_run.plan(spec, None, 8, (0.0, math.pi / 2)))


async def test_a_track_survey_through_the_daemon_writes_the_corner_and_the_radius(
    tmp_path: Path,
) -> None:
    spec = hall_rig(mount_sigma=(0.5, 5e-4), placement_sigma=(0.5, 3e-4))
    rng = np.random.default_rng(31)
    truth, delta, dr = cornered_truth(spec, rng)
    args = {"stations_mm": [3300.0, 4450.0, 5100.0], "samples": 3, "speed_mm_s": 2000.0}
    home = 3300.0  # the controller's zero near the corner: a short drive to the stations
    async with sensed_daemon(tmp_path, spec, truth, home, 31) as bench:
        result = await run_op(bench.client, "survey_track", args)
    assert result["passed"], result["reasons"]
    assert result["written"] == str(bench.rig_path)
    assert Path(result["report"]).is_file()
    new = load_rig(bench.rig_path)
    assert abs(new.track.home.value - home - delta) < 3 * result["corner_sigma_mm"]
    arcs = [s.radius_mm for s in new.track.segments if s.kind == "arc"]
    assert abs(arcs[0] - 1000.0 - dr) < 3 * result["radius_sigma_mm"]
    moved = np.linalg.inv(spec.track.placement.matrix) @ new.track.placement.matrix
    assert np.allclose(moved, make_T(np.eye(3), [-result["corner_mm"], 0.0, 0.0]), atol=1e-9)


async def test_a_failed_track_survey_writes_nothing(tmp_path: Path) -> None:
    spec = hall_rig()
    rng = np.random.default_rng(32)
    truth, _, _ = cornered_truth(spec, rng)
    async with sensed_daemon(tmp_path, spec, truth, HOME_MM, 32) as bench:
        before = bench.rig_path.read_bytes()
        result = await run_op(
            bench.client, "survey_track", {"stations_mm": [1000.0], "pans": 3,
                                           "speed_mm_s": 2000.0},
        )  # fmt: skip
    assert not result["passed"]
    assert result["written"] is None
    assert Path(result["report"]).is_file()
    assert bench.rig_path.read_bytes() == before
