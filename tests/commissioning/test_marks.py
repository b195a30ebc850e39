"""Reference marks from the rangefinder at rest past each capture: honest σ, refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.commissioning.marks_run import (
    OVERSHOOT_MM,
    Crossing,
    MarkThresholds,
    choose_aim,
    judge,
    marks_update,
    match_window,
    solve_mark,
    unmatched,
)
from host.commissioning.range_model import kinematics_of
from host.rig import RigSpec, with_updates
from tests.commissioning.rangefinder_truth import Truth, draw_truth, hall_rig

HOME_MM = 150.0  # the rig file's home (the controller's zero on the host's track)
SAMPLES = 20
LIMITS = (-math.pi, math.pi), (0.0, math.pi / 2)


def crossing(spec: RigSpec, truth: Truth, k: int, rng: np.random.Generator,
             aim: tuple[float, float] | None = None) -> Crossing:  # fmt: skip
    """What crossing mark k gives on the true rig: the controller's capture, rest and reading."""
    rig, hall = kinematics_of(spec)
    assert hall is not None
    nominal = spec.track.marks.s_mm[k]
    edge = truth.marks_mm[k] - HOME_MM - truth.shift_mm  # the controller's count at the edge
    rest = edge + OVERSHOOT_MM + rng.normal(0, 0.3)  # where it stopped
    pan, tilt = aim or choose_aim(spec, rig, hall, nominal + OVERSHOOT_MM, *LIMITS, SAMPLES)  # type: ignore[misc]
    d = truth.reading(rest + HOME_MM, pan, tilt)
    assert d is not None
    d += rng.normal(0, spec.rangefinder.noise_mm / math.sqrt(SAMPLES))
    return Crossing(k, nominal, edge, rest, pan, tilt, d, SAMPLES)


def test_marks_are_recovered_within_the_sigma_they_report() -> None:
    spec = hall_rig(mount_sigma=(0.5, 5e-4), placement_sigma=(0.5, 3e-4))
    rig, hall = kinematics_of(spec)
    assert hall is not None
    z = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        truth = draw_truth(spec, rng, mount_from_spec=True)
        results = [
            solve_mark(spec, rig, hall, HOME_MM, crossing(spec, truth, k, rng), 1.0)
            for k in range(len(spec.track.marks.s_mm))
        ]
        ok, reasons = judge(results, [], MarkThresholds())
        assert ok, reasons
        z += [(r.s_mm - m) / r.sigma_mm for r, m in zip(results, truth.marks_mm, strict=True)]
    zs = np.array(z)
    assert np.all(np.abs(zs) < 3.0), zs
    assert 0.4 < float(zs.std()) < 1.5, zs.std()
    update = marks_update(results, SAMPLES)["track.marks"]
    assert update.s_mm == tuple(sorted(r.s_mm for r in results))
    assert update.sigma_mm == pytest.approx(max(r.sigma_mm for r in results))
    assert with_updates(spec, {"track.marks": update}).track.marks is update


def test_the_home_does_not_enter_a_mark_measured_by_range() -> None:
    # a home off by 5 mm moves every capture, not the marks the walls fix
    spec = hall_rig(mount_sigma=(0.5, 5e-4), placement_sigma=(0.5, 3e-4))
    rig, hall = kinematics_of(spec)
    assert hall is not None
    rng = np.random.default_rng(7)
    truth = draw_truth(spec, rng, mount_from_spec=True, shift_sigma_mm=0.0)
    for shift in (-5.0, 5.0):
        moved = Truth(truth.rig, truth.scene, shift, truth.marks_mm)
        r = solve_mark(spec, rig, hall, HOME_MM, crossing(spec, moved, 2, rng), 1.0)
        assert abs(r.s_mm - truth.marks_mm[2]) < 3 * r.sigma_mm


def test_a_beam_across_the_track_is_refused() -> None:
    spec = hall_rig(mount_sigma=(0.5, 5e-4), placement_sigma=(0.5, 3e-4))
    rig, hall = kinematics_of(spec)
    assert hall is not None
    rng = np.random.default_rng(1)
    truth = draw_truth(spec, rng, mount_from_spec=True)
    sideways = (math.pi / 2, math.pi / 2)  # level, square to the first straight
    r = solve_mark(spec, rig, hall, HOME_MM, crossing(spec, truth, 1, rng, sideways), 1.0)
    assert "across the track" in r.problem
    ok, reasons = judge([r], [], MarkThresholds())
    assert not ok
    assert "across the track" in reasons[0]
    with pytest.raises(ValueError, match="only a complete"):
        marks_update([r], SAMPLES)


def test_missing_and_unmatched_marks_fail() -> None:
    spec = hall_rig(mount_sigma=(0.5, 5e-4), placement_sigma=(0.5, 3e-4))
    rig, hall = kinematics_of(spec)
    assert hall is not None
    rng = np.random.default_rng(2)
    truth = draw_truth(spec, rng, mount_from_spec=True)
    good = solve_mark(spec, rig, hall, HOME_MM, crossing(spec, truth, 0, rng), 1.0)
    c = crossing(spec, truth, 1, rng)
    none = Crossing(c.index, c.nominal_mm, None, c.rest_mm, c.pan_rad, c.tilt_rad,
                    c.distance_mm, c.count)  # fmt: skip
    missing = solve_mark(spec, rig, hall, HOME_MM, none, 1.0)
    ok, reasons = judge([good, missing], [], MarkThresholds())
    assert not ok
    assert "missing" in reasons[0]
    marks = spec.track.marks.s_mm
    window = match_window(marks)
    captures = [marks[0] - HOME_MM + 3.0, marks[0] - HOME_MM + 500.0]  # a stray half-way
    strays = unmatched(captures, marks, HOME_MM, window)
    assert strays == [pytest.approx(marks[0] + 500.0)]
    ok, reasons = judge([good], strays, MarkThresholds())
    assert not ok
    assert "unmatched" in reasons[0]


def test_an_uncalibrated_mount_gives_an_honest_sigma_that_fails() -> None:
    spec = hall_rig()  # nominal mount (3 mm, 3 mrad) and placement (5 mm)
    rig, hall = kinematics_of(spec)
    assert hall is not None
    rng = np.random.default_rng(5)
    truth = draw_truth(spec, rng, mount_from_spec=True)
    r = solve_mark(spec, rig, hall, HOME_MM, crossing(spec, truth, 3, rng), 1.0)
    assert not r.problem
    assert r.sigma_mm > 2.0
    assert abs(r.s_mm - truth.marks_mm[3]) < 3 * r.sigma_mm
    ok, reasons = judge([r], [], MarkThresholds())
    assert not ok
    assert "σ" in reasons[0]


def test_a_survey_of_some_marks_keeps_the_others() -> None:
    spec = hall_rig(mount_sigma=(0.5, 5e-4), placement_sigma=(0.5, 3e-4))
    rig, hall = kinematics_of(spec)
    assert hall is not None
    rng = np.random.default_rng(9)
    truth = draw_truth(spec, rng, mount_from_spec=True)
    some = [
        solve_mark(spec, rig, hall, HOME_MM, crossing(spec, truth, k, rng), 1.0) for k in (1, 4)
    ]
    listed = spec.track.marks
    update = marks_update(some, SAMPLES, listed)["track.marks"]
    assert len(update.s_mm) == len(listed.s_mm)
    assert update.s_mm[1] == pytest.approx(some[0].s_mm)
    assert update.s_mm[4] == pytest.approx(some[1].s_mm)
    assert update.s_mm[0] == listed.s_mm[0]
    assert update.sigma_mm == max(listed.sigma_mm, *(r.sigma_mm for r in some))
