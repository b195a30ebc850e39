"""The rangefinder mount from readings on the surveyed hall: honest σ, outliers, degeneracy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.commissioning.rangefinder_run import (
    MOUNT_AXES,
    MountThresholds,
    RangeSample,
    default_plan,
    fit_mount,
    mount_update,
)
from host.geometry.transforms import R_to_rotvec
from host.rig import RigSpec, with_updates
from tests.commissioning.rangefinder_truth import Truth, draw_truth, hall_rig

SAMPLES = 5


def readings(spec: RigSpec, truth: Truth, rng: np.random.Generator, plan: list) -> list:  # type: ignore[type-arg]
    """One mean of SAMPLES noisy readings per pose of the plan (poses with no hit skipped)."""
    out = []
    noise = spec.rangefinder.noise_mm / math.sqrt(SAMPLES)
    for v in plan:
        d = truth.reading(v.s_mm, v.pan_rad, v.tilt_rad)
        if d is not None:
            out.append(RangeSample(v.s_mm, v.pan_rad, v.tilt_rad, d + rng.normal(0, noise),
                                   1.0, SAMPLES))  # fmt: skip
    return out


def plan_for(spec: RigSpec) -> list:  # type: ignore[type-arg]
    return default_plan(spec, None, 8, None, (spec.head.tilt_min_rad, spec.head.tilt_max_rad))


def mount_error(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """truth = est · exp(δ): the solved components of δ."""
    d = np.linalg.inv(est) @ truth
    return np.concatenate([R_to_rotvec(d[:3, :3]), d[:3, 3]])[list(MOUNT_AXES)]


def test_the_mount_is_recovered_within_the_sigma_it_reports() -> None:
    spec = hall_rig()
    plan = plan_for(spec)
    assert len(plan) >= 60
    z = []
    for seed in range(4):
        rng = np.random.default_rng(seed)
        truth = draw_truth(spec, rng)
        fit = fit_mount(spec, readings(spec, truth, rng, plan))
        assert fit.passed, fit.reasons
        assert fit.T_r_l is not None
        assert fit.sigma is not None
        z.append(mount_error(fit.T_r_l, truth.rig.T_r_l) / fit.sigma)
        assert fit.shift_mm == pytest.approx(truth.shift_mm, abs=3 * fit.shift_sigma_mm)
    zs = np.array(z)
    assert np.all(np.abs(zs) < 3.0), zs
    assert 0.4 < float(zs.std()) < 1.5, zs  # σ neither far too small nor far too large
    # what the rig file gets: the mount, a covariance over all six, the roll's σ kept
    update = mount_update(fit)["rangefinder.mount"]
    assert update.covariance.shape == (6, 6)
    assert math.sqrt(update.covariance[2, 2]) == pytest.approx(spec.rangefinder.mount.sigma_rad[2])
    assert with_updates(spec, {"rangefinder.mount": update}).rangefinder.mount is update


def test_readings_on_an_unsurveyed_object_are_rejected() -> None:
    spec = hall_rig()
    rng = np.random.default_rng(11)
    truth = draw_truth(spec, rng)
    got = readings(spec, truth, rng, plan_for(spec))
    bad = [3, 17, 40]
    for i in bad:  # a ladder in the beam: far shorter than the wall
        x = got[i]
        got[i] = RangeSample(x.s_mm, x.pan_rad, x.tilt_rad, x.distance_mm - 800.0, 1.0, SAMPLES)
    fit = fit_mount(spec, got)
    assert fit.passed, fit.reasons
    assert sorted(np.flatnonzero(~fit.inliers).tolist()) == bad
    assert fit.T_r_l is not None
    assert fit.sigma is not None
    assert np.all(np.abs(mount_error(fit.T_r_l, truth.rig.T_r_l) / fit.sigma) < 3.0)


def test_all_readings_from_one_pose_fail_with_a_clear_message() -> None:
    spec = hall_rig()
    rng = np.random.default_rng(2)
    truth = draw_truth(spec, rng)
    one = plan_for(spec)[5]
    fit = fit_mount(spec, readings(spec, truth, rng, [one] * 40))
    assert not fit.passed
    assert fit.T_r_l is None
    assert "all readings come from one pose" in fit.reasons[0]
    with pytest.raises(ValueError, match="only a passing"):
        mount_update(fit)


def test_poses_that_cannot_separate_the_mount_fail() -> None:
    # the floor only, from one station: the beam origin's horizontal offset is unobservable
    spec = hall_rig()
    rng = np.random.default_rng(3)
    truth = draw_truth(spec, rng)
    plan = default_plan(spec, [2000.0], 24, [0.25], (0.0, math.pi / 2))
    assert plan
    fit = fit_mount(spec, readings(spec, truth, rng, plan))
    assert not fit.passed
    assert any("singular" in r or "condition" in r or "σ" in r for r in fit.reasons), fit.reasons


def test_a_stricter_threshold_fails_a_noisy_rangefinder() -> None:
    spec = hall_rig()
    rng = np.random.default_rng(4)
    truth = draw_truth(spec, rng)
    got = readings(spec, truth, rng, plan_for(spec))
    noisy = [
        RangeSample(x.s_mm, x.pan_rad, x.tilt_rad, x.distance_mm + rng.normal(0, 3.0), 1.0, 5)
        for x in got
    ]
    fit = fit_mount(spec, noisy, MountThresholds(max_rms_mm=1.0))
    assert not fit.passed
    assert any("RMS residual" in r for r in fit.reasons)


def test_the_plan_sweeps_the_pan_one_way_per_station_and_tilt() -> None:
    # the pan axis stops at ±180°: +150° to −150° is 300° of turning, not 60°
    plan = plan_for(hall_rig())
    sweeps: dict[tuple[float, float], list[float]] = {}
    for v in plan:
        sweeps.setdefault((v.s_mm, v.tilt_rad), []).append(v.pan_rad)
    assert len(sweeps) > 1
    for pans in sweeps.values():
        steps = np.diff(pans)
        assert np.all(steps > 0) or np.all(steps < 0), pans
        assert abs(pans[-1] - pans[0]) < math.tau * 7 / 8 + 1e-9
