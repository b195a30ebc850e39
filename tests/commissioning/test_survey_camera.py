"""The camera workpiece survey: targets found to a fraction of a pixel, triangulated, fitted."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hil_sim.camera import SyntheticCamera
from host.commissioning import targets_run
from host.commissioning.plan import ViewTarget
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import make_T, rotvec_to_R, transform_points
from host.rig import RigSpec, covariance_over, with_updates

FEATURES_P = np.array(
    [[300.0, 0.0, 150.0], [-300.0, 0.0, 150.0], [150.0, 150.0, 950.0],
     [80.0, 1279.0, 868.0], [70.0, 1239.0, 568.0]]
)  # fmt: skip
T_W_P = make_T(rotvec_to_R([0.001, -0.002, 0.003]), [-300.0, -300.0, 0.0])


def _views(
    rig: Rig, camera: CameraModel, T_w_p: np.ndarray, seed: int = 1
) -> list[targets_run.TargetView]:
    """Rendered views from three stations, targets found in them."""
    sim = SyntheticCamera(camera, seed=seed)
    model = manipulator_wireframe()
    points_w = transform_points(T_w_p, FEATURES_P)
    views = targets_run.plan_views(rig, camera, points_w, [-1200.0, -300.0, 600.0])
    for v in views:
        v.s_mm, v.head_rad = v.target.s_mm, (v.target.pan_rad, v.target.tilt_rad)
        T_w_c = rig.T_w_c(v.s_mm, *v.head_rad)
        img = sim.render_scene(T_w_c, model, T_w_p, targets_p=FEATURES_P).image
        uv, _ = camera.project(transform_points(np.linalg.inv(T_w_c), points_w[list(v.wanted)]))
        for k, p in zip(v.wanted, uv, strict=True):
            got = targets_run.find_target(img, p + np.array([6.0, -4.0]))  # a rough prediction
            if got is not None:
                v.found[k] = got
    return views


def test_a_target_is_found_to_a_small_fraction_of_a_pixel() -> None:
    camera = CameraModel()
    sim = SyntheticCamera(camera, seed=3)
    rig = Rig()
    points_w = transform_points(T_W_P, FEATURES_P)
    errors = []
    for view in targets_run.plan_views(rig, camera, points_w, [0.0]):
        T_w_c = rig.T_w_c(view.target.s_mm, view.target.pan_rad, view.target.tilt_rad)
        img = sim.render_scene(T_w_c, manipulator_wireframe(), T_W_P, targets_p=FEATURES_P).image
        uv, _ = camera.project(transform_points(np.linalg.inv(T_w_c), points_w[list(view.wanted)]))
        for p in uv:
            got = targets_run.find_target(img, p + np.array([-10.0, 8.0]))
            assert got is not None
            errors.append(float(np.hypot(*(got - p))))
    assert len(errors) == len(FEATURES_P)
    assert max(errors) < 0.1  # anti-aliased at 1/16 px, 1.5 DN of noise


def test_nothing_is_found_where_there_is_no_target() -> None:
    img = np.full((200, 200, 3), 110, np.uint8)
    assert targets_run.find_target(img, np.array([100.0, 100.0])) is None


def _exact(rig: Rig, track_cov: np.ndarray | None = None) -> RigSpec:
    """A rig file whose blocks are known exactly (but the placement's `track_cov`), σ 0."""
    nominal = RigSpec()
    zero = dataclasses.replace(nominal.head.m_cr, matrix=rig.T_r_c, covariance=np.zeros((6, 6)))
    placement = dataclasses.replace(
        nominal.track.placement, matrix=rig.track.T_w_track,
        covariance=np.zeros((6, 6)) if track_cov is None else track_cov,
    )  # fmt: skip
    intr = dataclasses.replace(nominal.camera.intrinsics, covariance=((0.0,) * 10,) * 10)
    home = dataclasses.replace(nominal.track.home, sigma=0.0)
    return dataclasses.replace(
        nominal,
        track=dataclasses.replace(nominal.track, placement=placement, home=home),
        head=dataclasses.replace(nominal.head, m_cr=zero),
        camera=dataclasses.replace(nominal.camera, intrinsics=intr),
    )


def test_the_frame_comes_back_through_the_rig_it_was_seen_with() -> None:
    rig, camera = Rig(), CameraModel()
    views = _views(rig, camera, T_W_P)
    out = targets_run.judge(views, rig, camera, FEATURES_P, _exact(rig))
    assert out.passed, out.reasons
    assert out.fit is not None
    assert out.covariance is not None
    d = np.linalg.inv(out.fit.T_w_p) @ T_W_P
    sig = np.sqrt(np.diag(out.covariance))
    assert np.all(np.abs(d[:3, 3]) < 0.5)  # mm
    assert np.all(np.abs(d[:3, 3]) < 4 * sig[3:] + 0.05)
    assert out.sigma_px < 0.2


def test_the_track_placement_uncertainty_is_carried_into_the_frame() -> None:
    rig, camera = Rig(), CameraModel()
    views = _views(rig, camera, T_W_P)
    track_cov = np.diag([1e-12] * 3 + [4.0] * 3)  # translation only: 2 mm
    out = targets_run.judge(views, rig, camera, FEATURES_P, _exact(rig, track_cov))
    assert out.passed
    assert out.covariance is not None
    assert np.sqrt(np.diag(out.covariance))[3:].min() == pytest.approx(2.0, rel=0.1)


def test_the_written_frame_shares_the_track_placement_error_it_was_seen_through() -> None:
    """The rig file gets the frame's cross terms with the placement: the workpiece's error
    relative to the track is the fit's alone, not the fit's plus twice the placement's."""
    rig, camera = Rig(), CameraModel()
    views = _views(rig, camera, T_W_P)
    track_cov = np.diag([1e-6] * 3 + [4.0] * 3)  # 1 mrad, 2 mm
    spec = _exact(rig, track_cov)
    out = targets_run.judge(views, rig, camera, FEATURES_P, spec)
    assert out.passed
    assert out.noise is not None
    written = with_updates(spec, targets_run.workpiece_update(out, spec))
    joint = covariance_over(written, ["track.placement", "workpiece.frame"])
    B = out.depends["track.placement"]
    relative = np.hstack([-B, np.eye(6)])  # δp − B δtrack: the frame against the track
    assert relative @ joint @ relative.T == pytest.approx(out.noise, abs=1e-9)
    assert np.sqrt(np.diag(joint[6:, 6:]))[3:].min() > 1.5  # absolute: the placement's 2 mm


def test_the_frame_moves_with_every_block_it_was_seen_through() -> None:
    """∂frame/∂block, as the survey writes it, against the frame a rig off by a small step
    finds from the same views: a track placed elsewhere carries the workpiece along whole,
    and M_cr, a focal length and the zero move it as the rays say."""
    rig, camera = Rig(), CameraModel()
    views = _views(rig, camera, T_W_P)
    out = targets_run.judge(views, rig, camera, FEATURES_P, _exact(rig))
    assert out.fit is not None
    shift = out.depends["track.placement"][:, 3:]  # a translation of the track, in its frame
    R_p_k = out.fit.T_w_p[:3, :3].T @ rig.track.T_w_track[:3, :3]
    assert shift[3:] == pytest.approx(R_p_k, abs=1e-6)
    assert np.abs(shift[:3]).max() < 1e-9

    def moved_by(vs: list[targets_run.TargetView], r: Rig, c: CameraModel) -> np.ndarray:
        again = targets_run.judge(vs, r, c, FEATURES_P, _exact(r))
        assert out.fit is not None
        assert again.fit is not None
        D: np.ndarray = np.linalg.inv(out.fit.T_w_p) @ again.fit.T_w_p
        return D[:3, 3]

    d_m = np.array([0.0, 0.0, 0.0, 0.5, -0.3, 0.2])  # M_cr off by half a millimetre
    off = dataclasses.replace(rig, T_r_c=rig.T_r_c @ make_T(rotvec_to_R(d_m[:3]), d_m[3:]))
    assert moved_by(views, off, camera) == pytest.approx(
        out.depends["head.m_cr"][3:] @ d_m, abs=0.02
    )
    d_c = np.zeros(10)
    d_c[0] = 5.0  # a focal length 5 px long
    longer = dataclasses.replace(camera, fx=camera.fx + 5.0)
    want = out.depends["camera.intrinsics"][3:] @ d_c
    assert moved_by(views, rig, longer) == pytest.approx(want, abs=0.02)
    ahead = [dataclasses.replace(v, s_mm=v.s_mm + 0.5) for v in views]  # the zero 0.5 mm on
    want = out.depends["track.home"][3:, 0] * 0.5
    assert moved_by(ahead, rig, camera) == pytest.approx(want, abs=0.02)


def test_one_view_per_target_is_refused_with_a_reason() -> None:
    rig, camera = Rig(), CameraModel()
    views = _views(rig, camera, T_W_P)[:1]
    out = targets_run.judge(views, rig, camera, FEATURES_P, _exact(rig))
    assert not out.passed
    assert "triangulated" in out.reasons[0]


def test_a_view_planned_per_station_sees_every_target() -> None:
    rig, camera = Rig(), CameraModel()
    points_w = transform_points(T_W_P, FEATURES_P)
    views = targets_run.plan_views(rig, camera, points_w, [0.0, 500.0])
    for s in (0.0, 500.0):
        seen = {k for v in views if v.target.s_mm == s for k in v.wanted}
        assert seen == set(range(len(FEATURES_P)))
    assert all(isinstance(v.target, ViewTarget) for v in views)
