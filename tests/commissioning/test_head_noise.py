"""The head's read noise measured at rest (host.commissioning.head_noise) and written by the
intrinsics run, read back through the rig file's codec."""

from __future__ import annotations

import numpy as np
import pytest

from host.calibration.board import Detection
from host.calibration.intrinsics import calibrate_with_rejection
from host.commissioning.head_noise import (
    METHOD,
    MIN_READINGS,
    REPORTED_RESOLUTION_RAD,
    angle_noise_update,
    read_noise,
    rest_sigma,
)
from host.commissioning.head_run import hand_eye_views
from host.commissioning.intrinsics_run import CapturedView, Outcome, rig_update
from host.commissioning.plan import ViewTarget
from host.geometry.camera import CameraModel
from host.geometry.transforms import euler_zyx, make_T
from host.rig import RigSpec, dumps_rig, loads_rig, with_updates
from host.rig.schema import HEAD_ANGLE_SIGMA_RAD, HEAD_RESOLUTION_RAD


def _rests(rng: np.random.Generator, sigma: float, rests: int, n: int) -> list[np.ndarray]:
    """Readings of a head standing at a different angle each rest, with Gaussian noise."""
    out = []
    for _ in range(rests):
        where = rng.uniform(-1.0, 1.0, 2)
        out.append(where + rng.normal(0.0, sigma, (n, 2)))
    return out


def test_the_scatter_about_each_rest_is_the_noise_as_read_and_as_looked_up() -> None:
    rng = np.random.default_rng(1)
    got = read_noise(_rests(rng, 3e-5, 15, 20))
    assert got is not None
    assert got.readings == 15 * 20 * 2
    assert got.raw_sigma_rad == pytest.approx(3e-5, rel=0.08)  # 570 dof: ±3 % (1σ)
    # the median of three of white noise: σ √0.449 ≈ 0.67 σ, less about the rest's mean as the
    # neighbouring medians share readings
    assert 0.5 * 3e-5 < got.sigma_rad < 0.7 * 3e-5


def test_a_head_on_its_counts_reads_the_jumps_only() -> None:
    """Standing on a count of 1e-4 rad with 2e-5 rad of noise before the rounding (as the
    simulator's plant): a reading is off by a count when the noise crosses half of one, 1.2 %
    of the time, so σ = √0.0124 · 1e-4 ≈ 1.1e-5 rad, a third of the datasheet's 3.5e-5."""
    rng = np.random.default_rng(2)
    q = 1e-4
    rests = []
    for _ in range(200):
        stand = np.round(rng.uniform(-1.0, 1.0, 2) / q) * q
        rests.append(np.round((stand + rng.normal(0.0, 2e-5, (20, 2))) / q) * q)
    got = read_noise(rests)
    assert got is not None
    expected = np.sqrt(2 * 0.5 * (1 - 0.98758)) * q  # P(|N(0, 2e-5)| > 5e-5) = 1.242 %
    assert got.raw_sigma_rad == pytest.approx(expected, rel=0.15)
    assert got.raw_sigma_rad < 0.5 * HEAD_ANGLE_SIGMA_RAD
    # a lone count off is dropped by the lookups' median: what is left is two in a row
    # (P ≈ 1.5e-4) and the floor of one count over the 7600 dof
    assert got.sigma_rad < 0.25 * got.raw_sigma_rad
    assert got.sigma_rad >= q / np.sqrt(200 * 2 * 19)


def test_a_reading_that_never_moved_is_not_taken_as_exact() -> None:
    """No step seen (rounding below the readings' 5 digits is none): σ is what one step of the
    datasheet's resolution over them would give."""
    rests = [np.full((10, 2), 0.25), np.full((10, 2), -0.5)]
    rests[0][3, 0] += 0.1 * REPORTED_RESOLUTION_RAD
    got = read_noise(rests)
    assert got is not None
    assert got.raw_sigma_rad == pytest.approx(HEAD_RESOLUTION_RAD / np.sqrt(2 * 2 * 9), rel=1e-3)
    assert got.sigma_rad == pytest.approx(got.raw_sigma_rad)  # the same step over the readings


def test_too_few_readings_keep_the_datasheet() -> None:
    few = [np.zeros((MIN_READINGS // 4, 2))]  # half the readings needed
    assert read_noise(few) is None
    assert angle_noise_update(few, 1) == {}
    assert read_noise([np.full((1, 2), np.nan)] * 100) is None  # no rest with two readings


def test_the_measured_noise_round_trips_through_the_rig_file() -> None:
    rng = np.random.default_rng(3)
    rests = _rests(rng, 1.5e-5, 12, 10)
    updates = angle_noise_update(rests, 12)
    spec = loads_rig(dumps_rig(with_updates(RigSpec(), updates)))
    noise = spec.head.angle_noise
    measured = read_noise(rests)
    assert measured is not None
    assert noise.sigma == pytest.approx(updates["head.angle_noise"].sigma)
    assert noise.sigma == pytest.approx(measured.sigma_rad)
    assert f"{measured.raw_sigma_rad:.2g} rad as read" in noise.provenance.note
    assert noise.provenance.method == METHOD
    assert noise.provenance.views == 12
    assert "240 readings over 12 rests" in noise.provenance.note


def test_the_intrinsics_run_writes_the_noise_its_views_measured() -> None:
    """`rig_update` of a passing intrinsics run: the lens and the head's noise at its rests."""
    rng = np.random.default_rng(4)
    camera = CameraModel()
    board = np.array([[x, y, 0.0] for x in range(0, 490, 70) for y in range(0, 350, 70)], float)
    poses = [
        make_T(euler_zyx(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3)),
               np.array([rng.uniform(-300, 100), rng.uniform(-250, 50), rng.uniform(2300, 2900)]))
        for _ in range(12)
    ]  # fmt: skip
    obj, img = [], []
    for T in poses:
        uv, _ = camera.project_world(T, board)
        obj.append(board)
        img.append(uv + rng.normal(0.0, 0.05, uv.shape))
    res = calibrate_with_rejection(obj, img, camera.size)
    views = [
        CapturedView(ViewTarget(0.0, 0.0, 0.0, f"v{i}"), "ok", rest_head_rad=r)
        for i, r in enumerate(_rests(rng, 2e-5, 12, 10))
    ]
    updates = rig_update(Outcome(True, [], views, res, camera))
    assert set(updates) == {"camera.intrinsics", "head.angle_noise"}
    measured = read_noise([v.rest_head_rad for v in views])
    assert measured is not None
    assert measured.raw_sigma_rad == pytest.approx(2e-5, rel=0.15)
    assert updates["head.angle_noise"].sigma == pytest.approx(measured.sigma_rad)
    quiet = [CapturedView(v.target, "ok") for v in views]  # no readings: the datasheet stays
    assert set(rig_update(Outcome(True, [], quiet, res, camera))) == {"camera.intrinsics"}


def test_a_head_standing_at_its_pan_stop_by_pi_reads_its_noise_not_the_wrap() -> None:
    rng = np.random.default_rng(5)
    rests = [np.array([np.pi, 0.3]) + rng.normal(0.0, 3e-5, (20, 2)) for _ in range(6)]
    rests = [np.remainder(r + np.pi, 2 * np.pi) - np.pi for r in rests]  # as read: ±π
    got = read_noise(rests)
    assert got is not None
    assert got.raw_sigma_rad == pytest.approx(3e-5, rel=0.2)


@pytest.mark.parametrize("n", [3, 5, 10, 20])
def test_a_rests_median_reads_as_rest_sigma_says(n: int) -> None:
    """The σ of a median of n Gaussian readings, from that of a median of three: within 10 %."""
    rng = np.random.default_rng(n)
    three = float(np.std(np.median(rng.normal(0.0, 1.0, (40_000, 3)), axis=1)))
    of_n = float(np.std(np.median(rng.normal(0.0, 1.0, (40_000, n)), axis=1)))
    assert rest_sigma(three, n) == pytest.approx(of_n, rel=0.1)
    assert rest_sigma(three, 1) == three  # a lone reading: the looked-up σ stands


def test_a_hand_eye_view_carries_the_sigma_of_its_own_rest() -> None:
    """`calibrate head` gives each view the looked-up σ scaled to its rest's readings."""
    det = Detection(np.arange(4, dtype=np.int32), np.zeros((4, 3)), np.zeros((4, 2)), 1.0)
    views = [
        CapturedView(ViewTarget(0.0, 0.0, 0.0, f"v{n}"), "ok", det, s_mm=10.0, head_rad=(0.1, 0.2),
                     rest_head_rad=np.zeros((n, 2)))
        for n in (0, 3, 12)
    ]  # fmt: skip
    got = [v.head_sigma_rad for v in hand_eye_views(views, 2e-5)]
    assert got == pytest.approx([2e-5, 2e-5, 1e-5])
