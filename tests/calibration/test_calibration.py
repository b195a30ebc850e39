"""Intrinsics from rendered chessboards and hand-eye from synthetic views."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hil_sim.camera import SyntheticCamera, chessboard_points
from host.calibration.handeye import HandEyeView, calibrate_handeye
from host.calibration.intrinsics import calibrate_intrinsics, find_chessboard
from host.geometry.camera import CameraModel
from host.geometry.head import M_CR_DEFAULT, Rig
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import (
    R_to_rotvec,
    euler_zyx,
    make_T,
    rot_z,
    rotation_angle,
    transform_points,
)

PATTERN = (9, 7)
SQUARE_MM = 60.0
BOARD_CENTRE = np.array([(PATTERN[0] - 1) * SQUARE_MM / 2, (PATTERN[1] - 1) * SQUARE_MM / 2, 0])


def board_pose(rng: np.random.Generator) -> np.ndarray:
    """A tilted board 2.6-3.2 m in front of the camera, centred near the optical axis."""
    R = euler_zyx(*rng.uniform([-0.6, -0.6, -0.5], [0.6, 0.6, 0.5]))
    centre = np.array([rng.uniform(-100, 100), rng.uniform(-80, 80), rng.uniform(2600, 3200)])
    return make_T(R, centre - R @ BOARD_CENTRE)


def test_intrinsics_recovered_from_rendered_chessboards() -> None:
    truth = CameraModel()  # Table 1 with its k1 = 1.30, k2 = 1.88 and skew 0.263
    sim = SyntheticCamera(truth, seed=1)
    rng = np.random.default_rng(3)
    obj, img = [], []
    for _ in range(14):
        frame = sim.render_chessboard(board_pose(rng), PATTERN, SQUARE_MM)
        corners = find_chessboard(frame.image, PATTERN)
        if frame.visible and corners is not None:
            # OpenCV may number a symmetric board from the opposite corner
            err = min(np.abs(c - frame.corners_uv).max() for c in (corners, corners[::-1]))
            assert err < 0.3
            obj.append(chessboard_points(PATTERN, SQUARE_MM))
            img.append(corners)
    assert len(obj) >= 12
    res = calibrate_intrinsics(obj, img, truth.size)
    cam = res.camera
    for key in ("fx", "fy", "u0", "v0"):
        assert getattr(cam, key) == pytest.approx(getattr(truth, key), rel=5e-3), key
    # k1 multiplies r² ≤ 0.05 over a 20° field: determined to ~0.4 % (its σ here), so judged by
    # it; k2 multiplies r⁴ ≤ 0.0025: only statistically determined.
    for key in ("k1", "k2"):
        assert abs(getattr(cam, key) - getattr(truth, key)) < 3.0 * res.std[key], key
    assert res.std["k1"] < 5e-3 * truth.k1
    assert res.rms_px < 0.2
    assert res.to_config()["camera"]["fx"] == cam.fx


def handeye_views(rig: Rig, T_w_b: np.ndarray, n: int, seed: int) -> list[HandEyeView]:
    """Views of a floor board from around the runway, pixel noise 0.1 px."""
    rng = np.random.default_rng(seed)
    cam = CameraModel()
    X = chessboard_points(PATTERN, SQUARE_MM)
    centre = transform_points(T_w_b, BOARD_CENTRE)
    views: list[HandEyeView] = []
    while len(views) < n:
        s = rng.uniform(0.0, rig.track.length_mm)
        pan, tilt = rig.aim(s, centre)
        pan, tilt = pan + rng.uniform(-0.03, 0.03), tilt + rng.uniform(-0.03, 0.03)
        uv, valid = cam.project_world(rig.T_c_w(s, pan, tilt) @ T_w_b, X)
        inside = (uv > 0).all() and (uv[:, 0] < cam.width).all() and (uv[:, 1] < cam.height).all()
        if valid.all() and inside:
            views.append(HandEyeView(s, pan, tilt, X, uv + rng.normal(0, 0.1, uv.shape)))
    return views


def test_handeye_recovers_m_cr_and_track_origin() -> None:
    rig = Rig()
    T_w_b = make_T(rot_z(0.3), [-200.0, -1400.0, 0.0])
    views = handeye_views(rig, T_w_b, 20, seed=0)
    local = rig.track.with_origin(np.eye(4))
    res = calibrate_handeye(views, local, CameraModel(), T_w_b=T_w_b)
    assert float(rotation_angle(res.M_cr[:3, :3].T @ M_CR_DEFAULT[:3, :3])) < 1e-4
    assert np.linalg.norm(res.M_cr[:3, 3] - M_CR_DEFAULT[:3, 3]) < 0.5
    assert np.linalg.norm(res.T_w_track[:3, 3] - rig.track.T_w_track[:3, 3]) < 1.0
    assert res.rms_px < 0.2
    assert res.rms_px <= res.initial_rms_px
    # per-view PnP poses at 4 m through a 20° lens are themselves uncertain to ~1 mrad, 1 mm
    assert res.rotation_residual_rad.max() < 3e-3
    assert res.translation_residual_mm.max() < 3.0
    assert res.per_view_rms_px.shape == (20,)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_handeye_sigma_is_what_it_achieves(seed: int) -> None:
    """Off-nominal M_cr, noisy views: each of the 12 local errors within 3 reported σ."""
    rng = np.random.default_rng(seed + 100)
    M = M_CR_DEFAULT @ make_T(euler_zyx(*rng.normal(0, 3e-3, 3)), rng.normal(0, 3.0, 3))
    rig = Rig(T_r_c=M)
    T_w_b = make_T(rot_z(0.3), [-200.0, -1400.0, 0.0])
    views = handeye_views(rig, T_w_b, 15, seed=seed)
    local = rig.track.with_origin(np.eye(4))
    res = calibrate_handeye(views, local, CameraModel(), T_w_b=T_w_b)
    err_m = local_error(res.M_cr, M)
    err_k = local_error(res.T_w_track, rig.track.T_w_track)
    sig_m = np.sqrt(np.diag(res.cov_M_cr))
    sig_k = np.sqrt(np.diag(res.track_covariance))
    assert np.all(np.abs(err_m) < 3 * sig_m), (err_m, sig_m)
    assert np.all(np.abs(err_k) < 3 * sig_k), (err_k, sig_k)


def test_handeye_moves_with_the_zero_as_its_cross_term_says() -> None:
    """Every view's arc length off by the same δs (the zero's error): the solution moves by
    home_cross / σ² · δs, which the rig file's cross terms with `track.home` carry (on the
    straight the board is seen from, the placement takes it up along the track)."""
    rig = Rig()
    T_w_b = make_T(rot_z(0.3), [-200.0, -1400.0, 0.0])
    views = handeye_views(rig, T_w_b, 15, seed=4)
    local = rig.track.with_origin(np.eye(4))
    sigma, ds = 5.0, 0.5
    exact = calibrate_handeye(views, local, CameraModel(), T_w_b=T_w_b, home_sigma_mm=sigma)
    shifted = [dataclasses.replace(v, s_mm=v.s_mm + ds) for v in views]
    off = calibrate_handeye(shifted, local, CameraModel(), T_w_b=T_w_b, home_sigma_mm=sigma)
    assert exact.home_cross is not None
    moved = np.concatenate(
        [local_error(exact.M_cr, off.M_cr), local_error(exact.T_b_track, off.T_b_track)]
    )
    predicted = exact.home_cross / sigma**2 * ds
    assert np.allclose(moved, predicted, atol=0.03 * np.abs(predicted).max()), (moved, predicted)
    assert np.abs(predicted[9:]).max() > 0.5 * ds  # the placement takes most of it up
    # and its variance is in the covariance: Cov(x, s)² ≤ Var(x) σ² (Cauchy-Schwarz)
    assert np.all(exact.home_cross**2 <= np.diag(exact.covariance) * sigma**2 * (1 + 1e-9))


def local_error(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """δ with truth = est · exp(δ), as (rotation vector, translation)."""
    d = np.linalg.inv(est) @ truth
    return np.concatenate([R_to_rotvec(d[:3, :3]), d[:3, 3]])


def test_synthetic_scene_keeps_ground_truth() -> None:
    rig, cam = Rig(), CameraModel()
    sim = SyntheticCamera(cam, seed=4)
    pan, tilt = rig.aim(1000.0, [0.0, 600.0, 800.0])
    T_w_c = rig.T_w_c(1000.0, pan, tilt)
    pts = np.array([[0.0, 0.0, 150.0], [0.0, 600.0, 800.0]])
    frame = sim.render_scene(T_w_c, manipulator_wireframe(), np.eye(4), pts)
    assert frame.image.shape == (cam.height, cam.width, 3)
    u, v = np.rint(frame.points_uv[1]).astype(int)
    assert abs(u - cam.u0) < 2  # the aimed point lands on the principal point
    assert abs(v - cam.v0) < 2
    assert (np.abs(frame.image.astype(int) - 110).sum(axis=2) > 60).sum() > 1000
    again = SyntheticCamera(cam, seed=4).render_scene(
        T_w_c, manipulator_wireframe(), np.eye(4), pts
    )
    np.testing.assert_array_equal(frame.image, again.image)


def test_each_views_head_sigma_adds_its_own_share() -> None:
    """The head angles' share is per view: none without σ, and with σ on every view the sum of
    what each view's σ alone adds (their errors are independent)."""
    rig = Rig()
    T_w_b = make_T(rot_z(0.3), [-200.0, -1400.0, 0.0])
    views = handeye_views(rig, T_w_b, 8, seed=5)
    local = rig.track.with_origin(np.eye(4))

    def cov(sigmas: list[float]) -> np.ndarray:
        with_sigma = [
            dataclasses.replace(v, head_sigma_rad=s) for v, s in zip(views, sigmas, strict=True)
        ]
        return calibrate_handeye(with_sigma, local, CameraModel(), T_w_b=T_w_b).cov_M_cr

    plain = cov([0.0] * len(views))
    shares = [cov([3e-5 if j == i else 0.0 for j in range(len(views))]) - plain
              for i in range(len(views))]  # fmt: skip
    every = cov([3e-5] * len(views)) - plain
    assert np.trace(every) > 0.1 * np.trace(plain)  # the share is not lost in the pixel noise
    assert np.allclose(every, sum(shares), rtol=1e-6, atol=1e-6 * np.abs(every).max())
