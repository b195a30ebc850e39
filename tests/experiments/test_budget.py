"""The error budget: first-order overlay σ against a Monte Carlo of the same inputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from host.calibration.handeye import adjoint
from host.experiments.budget import (
    N_INPUTS,
    SLICES,
    BudgetInputs,
    inputs_from_rig,
    jacobian,
    monte_carlo,
    overlay_sigma,
    visible,
)
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import FloatArray, invert_T, make_T
from host.rig import Provenance, RigSpec, Scalar, joint_covariance

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
        "home",
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


def _track_frame_workpiece(base: BudgetInputs) -> tuple[FloatArray, FloatArray]:
    """A workpiece known in the track's frame: δp = Ad(T_p_k) δk, so Cov(δp), Cov(δp, δk)."""
    T_p_k = invert_T(base.T_w_p) @ base.rig.track.T_w_track
    Ad = adjoint(T_p_k)
    return Ad @ base.track_cov @ Ad.T, Ad @ base.track_cov


def test_a_workpiece_sharing_the_track_error_cancels_it() -> None:
    """Camera and workpiece move together: the overlay does not see the track's error at all,
    while the same σ taken as independent adds the two shares."""
    track = np.diag([3e-4**2] * 3 + [4.0] * 3)
    base = dataclasses.replace(inputs(0.0), camera_cov=np.zeros((10, 10)),
                               m_cr_cov=np.zeros((6, 6)), track_cov=track, sigma_s_mm=0.0,
                               sigma_head_rad=(0.0, 0.0))  # fmt: skip
    cov_p, cross_pk = _track_frame_workpiece(base)
    cross = np.zeros((N_INPUTS, N_INPUTS))
    cross[SLICES["workpiece"], SLICES["track"]] = cross_pk
    cross[SLICES["track"], SLICES["workpiece"]] = cross_pk.T
    independent = dataclasses.replace(base, workpiece_cov=cov_p)
    shared = dataclasses.replace(independent, cross=cross)
    rig, points = Rig(), manipulator_wireframe().vertices
    pan, tilt = rig.aim(1500.0, WORKPIECE[:3, 3])
    alone = overlay_sigma(independent, 1500.0, pan, tilt, points)
    together = overlay_sigma(shared, 1500.0, pan, tilt, points)
    assert alone.sigma_px > 1.0
    assert alone.sigma_px == pytest.approx(
        np.hypot(alone.by_source_px["track"], alone.by_source_px["workpiece"]), rel=1e-6
    )
    assert together.sigma_px < 1e-3 * alone.sigma_px
    assert together.by_source_px["track"] == pytest.approx(alone.by_source_px["track"])


def test_correlated_first_order_matches_monte_carlo() -> None:
    """Strong cross terms (a focal length with M_cr's tz, the workpiece with the track): the
    first order and a Monte Carlo of the same joint inputs agree within 10 % (400 samples: the
    Monte Carlo's own σ is ~4 %)."""
    base = inputs(100.0)
    cov_p, cross_pk = _track_frame_workpiece(base)
    rng = np.random.default_rng(2)
    cross = np.zeros((N_INPUTS, N_INPUTS))
    cross[SLICES["workpiece"], SLICES["track"]] = 0.8 * cross_pk
    cross[SLICES["track"], SLICES["workpiece"]] = 0.8 * cross_pk.T
    fx, tz = 0, SLICES["m_cr"].start + 5
    c = -0.95 * np.sqrt(base.camera_cov[0, 0] * base.m_cr_cov[5, 5])
    cross[fx, tz] = cross[tz, fx] = c
    inp = dataclasses.replace(base, workpiece_cov=cov_p + np.eye(6) * 1e-8, cross=cross)
    assert np.linalg.eigvalsh(inp.covariance()).min() > -1e-12  # a valid joint covariance
    rig, points = Rig(), manipulator_wireframe().vertices[rng.permutation(60)[:30]]
    for s_mm in (500.0, 2500.0):
        pan, tilt = rig.aim(s_mm, WORKPIECE[:3, 3] + [0, 0, 300])
        first = overlay_sigma(inp, s_mm, pan, tilt, points)
        mc = monte_carlo(inp, s_mm, pan, tilt, points, n=400, seed=3)
        assert first.sigma_px == pytest.approx(mc, rel=0.1)
        plain = overlay_sigma(dataclasses.replace(inp, cross=None), s_mm, pan, tilt, points)
        assert first.sigma_px < plain.sigma_px  # the shared errors cancel in part


def test_a_correlated_pair_changes_the_variance_linearly_in_rho() -> None:
    """σ² = a² + b² + 2ρ·(J_a σ_a)·(J_b σ_b): from ρ = 0 to ±1 exactly as the pair's columns say."""
    base = dataclasses.replace(inputs(0.0), cross=None)
    rig, points = Rig(), manipulator_wireframe().vertices
    pan, tilt = rig.aim(800.0, WORKPIECE[:3, 3])
    fx, tz = 0, SLICES["m_cr"].start + 5
    J = jacobian(base, 800.0, pan, tilt, visible(base, 800.0, pan, tilt, points))
    sa, sb = np.sqrt(base.camera_cov[0, 0]), np.sqrt(base.m_cr_cov[5, 5])
    n = len(J) // 2
    dot = float(J[:, fx] @ J[:, tz]) * sa * sb / n
    cos = float(J[:, fx] @ J[:, tz]) / float(np.linalg.norm(J[:, fx]) * np.linalg.norm(J[:, tz]))
    assert abs(cos) > 0.5  # the focal length and the camera's depth do show alike
    var0 = overlay_sigma(base, 800.0, pan, tilt, points).sigma_px ** 2
    for rho in (-0.9, 0.9):
        cross = np.zeros((N_INPUTS, N_INPUTS))
        cross[fx, tz] = cross[tz, fx] = rho * sa * sb
        var = overlay_sigma(dataclasses.replace(base, cross=cross), 800.0, pan, tilt, points)
        assert var.sigma_px**2 == pytest.approx(var0 + 2 * rho * dot, rel=1e-6)
    # the sign that cancels lowers σ
    rho = -0.9 * np.sign(dot)
    cross = np.zeros((N_INPUTS, N_INPUTS))
    cross[fx, tz] = cross[tz, fx] = rho * sa * sb
    lower = overlay_sigma(dataclasses.replace(base, cross=cross), 800.0, pan, tilt, points)
    assert lower.sigma_px**2 < var0


def test_inputs_from_rig_carry_the_joint_block_head_noise_and_stamp_errors() -> None:
    spec = RigSpec()
    cam = spec.camera.intrinsics
    joint = joint_covariance(
        {"camera.intrinsics": np.diag(np.square(cam.sigma)), "head.m_cr": spec.head.m_cr.cov()},
        {("camera.intrinsics", "head.m_cr"): np.full((10, 6), 1e-9)},
        Provenance("test"),
    )
    spec = dataclasses.replace(
        spec,
        covariance=joint,
        head=dataclasses.replace(spec.head, angle_noise=Scalar(0.0, 4e-5)),
        camera=dataclasses.replace(spec.camera, clock_sync=Scalar(0.0, 0.5)),
    )
    inp = inputs_from_rig(spec, speed_mm_s=100.0)
    S = inp.covariance()
    assert S[0, SLICES["m_cr"].start] == 1e-9
    assert S[SLICES["m_cr"], SLICES["track"]].max() == 0.0  # not solved together
    assert inp.sigma_head_rad == (4e-5, 4e-5)
    stamp = np.hypot(0.5e-3, spec.camera.latency.sigma / 1e3)
    assert S[28, 28] == pytest.approx((stamp * 100.0) ** 2)  # the encoder counts from the zero
    assert S[31, 31] == spec.track.arc_radius_sigma_mm**2
    assert S[32, 32] == spec.track.home.sigma**2  # the zero's own, shared by what used it
