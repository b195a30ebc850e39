"""Transforms, track geometry, head chain and workpiece frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.geometry.head import M_CR_DEFAULT, M_CR_PAPER, Rig, head_rotation
from host.geometry.track import Track, runway
from host.geometry.transforms import (
    R_from_quat,
    R_to_rotvec,
    euler_zyx,
    euler_zyx_from_R,
    interpolate_T,
    invert_T,
    make_T,
    quat_from_R,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
    rotvec_to_R,
    slerp,
)
from host.geometry.workpiece import (
    rangefinder_point,
    workpiece_frame,
    workpiece_frame_from_features,
)


def random_T(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random rigid transforms with translations of metres."""
    R = rotvec_to_R(rng.normal(size=(n, 3)))
    return make_T(R, rng.uniform(-5000, 5000, size=(n, 3)))


def test_T_times_inverse_is_identity() -> None:
    T = random_T(np.random.default_rng(1), 50)
    np.testing.assert_allclose(T @ invert_T(T), np.broadcast_to(np.eye(4), T.shape), atol=1e-9)
    np.testing.assert_allclose(invert_T(T) @ T, np.broadcast_to(np.eye(4), T.shape), atol=1e-9)


def test_euler_matches_eq3_entries() -> None:
    a, b, g = 0.3, -0.7, 1.9
    R = euler_zyx(a, b, g)
    ca, sa, sb = math.cos(a), math.sin(a), math.sin(b)
    cg, sg = math.cos(g), math.sin(g)
    assert R[0, 1] == pytest.approx(sa * sb * cg - ca * sg)
    assert R[1, 2] == pytest.approx(ca * sb * sg - sa * cg)
    assert R[2, 0] == pytest.approx(-sb)
    np.testing.assert_allclose(R, rot_z(g) @ rot_y(b) @ rot_x(a))


def test_euler_round_trip() -> None:
    rng = np.random.default_rng(2)
    a, g = rng.uniform(-math.pi, math.pi, (2, 200))
    b = rng.uniform(-math.pi / 2 + 1e-3, math.pi / 2 - 1e-3, 200)
    a2, b2, g2 = euler_zyx_from_R(euler_zyx(a, b, g))
    np.testing.assert_allclose(np.stack([a2, b2, g2]), np.stack([a, b, g]), atol=1e-9)


def test_euler_gimbal_lock_reproduces_rotation() -> None:
    for beta in (math.pi / 2, -math.pi / 2):
        R = euler_zyx(0.4, beta, -0.3)
        a, b, g = euler_zyx_from_R(R)
        np.testing.assert_allclose(euler_zyx(a, b, g), R, atol=1e-9)


def test_quaternion_and_rotvec_round_trips_including_near_pi() -> None:
    rng = np.random.default_rng(3)
    rv = rng.normal(size=(300, 3))
    rv[:5] = rv[:5] / np.linalg.norm(rv[:5], axis=1, keepdims=True) * (math.pi - 1e-7)
    R = rotvec_to_R(rv)
    np.testing.assert_allclose(R_from_quat(quat_from_R(R)), R, atol=1e-12)
    np.testing.assert_allclose(rotvec_to_R(R_to_rotvec(R)), R, atol=1e-9)


def test_slerp_midpoint_is_half_angle() -> None:
    q0 = quat_from_R(np.eye(3))
    q1 = quat_from_R(rot_z(1.2))
    np.testing.assert_allclose(R_from_quat(slerp(q0, q1, 0.25)), rot_z(0.3), atol=1e-12)
    T = interpolate_T(make_T(np.eye(3), [0, 0, 0]), make_T(rot_x(0.8), [10, 0, 0]), 0.5)
    np.testing.assert_allclose(T, make_T(rot_x(0.4), [5, 0, 0]), atol=1e-12)


def test_runway_length_and_closure() -> None:
    track = runway()
    assert track.length_mm == pytest.approx(2 * (4000 + 1000) + 2 * math.pi * 1000, abs=1e-9)
    assert track.closed
    np.testing.assert_allclose(track.pose(track.length_mm), track.pose(0.0), atol=1e-9)
    np.testing.assert_allclose(track.position(0.0), [-2000, -1500, 4000])
    assert track.position(-1.0)[0] == pytest.approx(track.position(track.length_mm - 1.0)[0])


def test_arcs_bent_wider_keep_the_loop_closed_and_the_first_straight() -> None:
    t = runway()
    wider = t.with_arc_radius_change(3.0)
    assert wider.closed
    assert wider.length_mm == pytest.approx(t.length_mm + 4 * 3.0 * math.pi / 2)
    s = np.linspace(0.0, 4000.0, 9)  # the first straight
    assert np.allclose(wider.pose(s), t.pose(s))
    end = 4000.0 + 1003.0 * math.pi / 2  # the first arc's end: 3 mm further out and along
    assert np.allclose(wider.position(end) - t.position(4000.0 + 1000.0 * math.pi / 2),
                       [3.0, 3.0, 0.0], atol=1e-9)  # fmt: skip


def test_runway_positions_continuous_at_joints() -> None:
    track = runway()
    joints = np.cumsum([g.length_mm for g in track.segments])[:-1]
    eps = 1e-6
    before, after = track.pose(joints - eps), track.pose(joints + eps)
    np.testing.assert_allclose(before, after, atol=1e-5)


def test_heading_is_derivative_of_position() -> None:
    track = Track.from_config(
        [
            {"kind": "straight", "length_mm": 500},
            {"kind": "arc", "radius_mm": 800, "angle_deg": 70},
            {"kind": "arc", "radius_mm": 300, "angle_deg": -120},
        ]
    )
    assert not track.closed
    s = np.linspace(1.0, track.length_mm - 1.0, 400)
    h = 1e-4
    deriv = (track.position(s + h) - track.position(s - h)) / (2 * h)
    x_t = track.pose(s)[:, :3, 0]
    np.testing.assert_allclose(deriv, x_t, atol=1e-6)
    with pytest.raises(ValueError, match="outside"):
        track.pose(track.length_mm + 1.0)


def test_trolley_frame_is_right_handed_with_z_down() -> None:
    T = runway().pose(np.linspace(0, 16000, 33))
    np.testing.assert_allclose(np.linalg.det(T[:, :3, :3]), 1.0, atol=1e-12)
    np.testing.assert_allclose(T[:, :3, 2], np.tile([0, 0, -1.0], (33, 1)), atol=1e-12)


def test_bad_segments_and_false_closure_rejected() -> None:
    with pytest.raises(ValueError, match="kind"):
        Track.from_config([{"kind": "spiral"}])
    with pytest.raises(ValueError, match="closed"):
        Track.from_config([{"kind": "straight", "length_mm": 10}], closed=True)


def test_m_cr_default_is_orthonormal_and_near_paper() -> None:
    R = M_CR_DEFAULT[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert np.abs(R - M_CR_PAPER[:3, :3]).max() < 5e-3
    np.testing.assert_array_equal(M_CR_DEFAULT[:3, 3], M_CR_PAPER[:3, 3])


def test_head_rotation_axes_are_z_then_y() -> None:
    np.testing.assert_allclose(head_rotation(0.3, 0.0)[:3, :3], rot_z(0.3))
    np.testing.assert_allclose(head_rotation(0.3, -0.2)[:3, :3], rot_z(0.3) @ rot_y(-0.2))


def test_rig_chain_and_aim() -> None:
    rig = Rig()
    T = rig.T_w_c(1234.0, 0.2, -0.1)
    expected = rig.track.pose(1234.0) @ rig.T_t_r @ head_rotation(0.2, -0.1) @ rig.T_r_c
    np.testing.assert_allclose(T, expected)
    target = np.array([300.0, -800.0, 0.0])
    pan, tilt = rig.aim(1500.0, target)
    T_w_c = rig.T_w_c(1500.0, pan, tilt)
    d = (target - T_w_c[:3, 3]) / np.linalg.norm(target - T_w_c[:3, 3])
    assert float(d @ T_w_c[:3, 2]) > math.cos(1e-4)


def test_workpiece_frame_from_known_points() -> None:
    T_true = make_T(rotvec_to_R([0.2, -0.4, 1.1]), [1500.0, -300.0, 20.0])
    local = np.array([[0, 0, 0], [50, 80, 40], [0, 300, 200], [9, 9, 9], [0, 0, 700.0]])
    pts = local @ T_true[:3, :3].T + T_true[:3, 3]
    np.testing.assert_allclose(workpiece_frame_from_features(pts), T_true, atol=1e-9)
    T = workpiece_frame(pts[0], pts[2], pts[4])
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="collinear"):
        workpiece_frame([0, 0, 0], [0, 0, 5], [0, 0, 10])


def test_rangefinder_point_lies_on_optical_axis() -> None:
    rig = Rig()
    pan, tilt = rig.aim(2000.0, [100.0, -1000.0, 0.0])
    T = rig.T_w_c(2000.0, pan, tilt)
    p = rangefinder_point(rig, 2000.0, pan, tilt, 3000.0)
    np.testing.assert_allclose(p, T[:3, 3] + 3000.0 * T[:3, 2])
    pts = rangefinder_point(rig, [2000.0, 2000.0], [pan, pan], [tilt, tilt], [10.0, 20.0])
    assert pts.shape == (2, 3)
    assert rotation_angle(np.eye(3)) == 0.0
