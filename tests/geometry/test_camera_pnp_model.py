"""Camera projection against OpenCV, PnP solvers, and model loading."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from host.geometry.camera import CameraModel, Projector
from host.geometry.model import load_model, load_obj, load_ply, manipulator_wireframe
from host.geometry.pnp import solve_dlt, solve_sqpnp
from host.geometry.transforms import make_T, rotation_angle, rotvec_to_R

CAM0 = CameraModel(skew=0.0, p1=1e-3, p2=-5e-4, k3=0.5)


def points_in_view(rng: np.random.Generator, n: int) -> np.ndarray:
    """Camera-frame points inside roughly the field of view, 2-5 m away."""
    z = rng.uniform(2000, 5000, n)
    x = rng.uniform(-0.2, 0.2, n) * z
    y = rng.uniform(-0.16, 0.16, n) * z
    return np.stack([x, y, z], axis=1)


def test_projection_equals_cv2_at_skew_zero() -> None:
    rng = np.random.default_rng(5)
    P = points_in_view(rng, 2000)
    T = make_T(rotvec_to_R([0.1, -0.2, 0.3]), [100.0, -50.0, 300.0])
    Pw = (P - T[:3, 3]) @ T[:3, :3]  # world points that T maps back to P
    ref, _ = cv2.projectPoints(Pw, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], CAM0.K, CAM0.dist)
    uv, valid = CAM0.project_world(T, Pw)
    assert valid.all()
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6, rtol=0)
    fast, fvalid = Projector(CAM0, Pw).project(T)
    np.testing.assert_allclose(fast.T, ref.reshape(-1, 2), atol=1e-6, rtol=0)
    assert fvalid.all()


def test_projection_without_tangential_matches_fast_path() -> None:
    cam = CameraModel()  # Table 1, with skew
    P = points_in_view(np.random.default_rng(6), 500)
    uv, _ = cam.project(P)
    fast, _ = Projector(cam, P).project(np.eye(4))
    np.testing.assert_allclose(fast.T, uv, atol=1e-9)
    # skew moves u by skew · y_d: the model is ours, not OpenCV's
    uv0, _ = CameraModel(skew=0.0).project(P)
    assert not np.allclose(uv, uv0, atol=1e-3)


def test_points_behind_camera_are_masked() -> None:
    P = np.array([[0, 0, 1000.0], [0, 0, -1000.0], [10, 0, 0.0]])
    uv, valid = CameraModel().project(P)
    assert valid.tolist() == [True, False, False]
    assert np.isnan(uv[1:]).all()
    fast, fvalid = Projector(CameraModel(), P).project(np.eye(4))
    assert fvalid.tolist() == [True, False, False]
    assert np.isnan(fast[:, 1:]).all()


def test_undistort_inverts_projection() -> None:
    cam = CameraModel(p1=1e-3, p2=-5e-4)
    P = points_in_view(np.random.default_rng(7), 500)
    uv, _ = cam.project(P)
    n = cam.undistort_normalized(uv)
    np.testing.assert_allclose(n, P[:, :2] / P[:, 2:], atol=1e-10)


def test_camera_config_round_trip_and_K() -> None:
    cam = CameraModel()
    assert CameraModel.from_config(cam.to_config()) == cam
    assert cam.K[0, 1] == pytest.approx(0.263)
    with pytest.raises(ValueError, match="unknown"):
        CameraModel.from_config({"focal": 1.0})


def scene(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, CameraModel]:
    """Non-coplanar world points and a pose that sees them."""
    cam = CameraModel()
    T = make_T(rotvec_to_R([0.3, -0.2, 2.0]), [150.0, -80.0, 3500.0])
    Pc = points_in_view(rng, n) * np.array([1, 1, 0.3]) + np.array([0, 0, 2500.0])
    Pw = (Pc - T[:3, 3]) @ T[:3, :3]
    return Pw, T, cam


@pytest.mark.parametrize("solver", [solve_dlt, solve_sqpnp])
def test_pnp_recovers_pose_from_noiseless_points(solver) -> None:  # type: ignore[no-untyped-def]
    Pw, T, cam = scene(np.random.default_rng(8), 12)
    uv, _ = cam.project_world(T, Pw)
    res = solver(Pw, uv, cam)
    assert float(rotation_angle(res.T_c_w[:3, :3].T @ T[:3, :3])) < 1e-6
    assert np.linalg.norm(res.T_c_w[:3, 3] - T[:3, 3]) < 1e-6 * np.linalg.norm(T[:3, 3])
    assert res.rms_px < 1e-6


def test_dlt_degrades_gracefully_with_noise() -> None:
    rng = np.random.default_rng(9)
    Pw, T, cam = scene(rng, 40)
    uv, _ = cam.project_world(T, Pw)
    errors = []
    for sigma in (0.1, 1.0, 5.0):
        runs = [solve_dlt(Pw, uv + rng.normal(0, sigma, uv.shape), cam) for _ in range(20)]
        errors.append(np.median([np.linalg.norm(r.T_c_w[:3, 3] - T[:3, 3]) for r in runs]))
        rot = max(float(rotation_angle(r.T_c_w[:3, :3].T @ T[:3, :3])) for r in runs)
        assert rot < 0.02 * sigma  # bounded: 0.02 rad per pixel of noise
    assert errors[0] < errors[1] < errors[2]
    assert errors[2] < 200.0  # mm at 3.5 m with 5 px noise


def test_dlt_rejects_too_few_and_coplanar_points() -> None:
    Pw, T, cam = scene(np.random.default_rng(10), 12)
    uv, _ = cam.project_world(T, Pw)
    with pytest.raises(ValueError, match="at least 6"):
        solve_dlt(Pw[:5], uv[:5], cam)
    flat = Pw.copy()
    flat[:, 2] = 0.0
    uvf, _ = cam.project_world(T, flat)
    with pytest.raises(ValueError, match="degenerate"):
        solve_dlt(flat, uvf, cam)
    assert solve_sqpnp(flat, uvf, cam).rms_px < 1e-6


def test_load_obj(tmp_path: Path) -> None:
    p = tmp_path / "quad.obj"
    p.write_text(
        "# a square and a tail\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 2 2\n"
        "f 1/1/1 2/2/2 3//3 -2\nl 3 5\n"
    )
    m = load_obj(p)
    assert m.vertices.shape == (5, 3)
    assert sorted(map(tuple, m.edges.tolist())) == [(0, 1), (0, 3), (1, 2), (2, 3), (2, 4)]
    assert m.faces.shape == (2, 3)
    (tmp_path / "bad.obj").write_text("v 0 0 0\nf 1 7 x\n")
    with pytest.raises(ValueError, match="bad OBJ"):
        load_obj(tmp_path / "bad.obj")


def ply_header(fmt: str) -> str:
    """Header of a 4-vertex, 1-quad, 1-edge PLY."""
    return (
        f"ply\nformat {fmt} 1.0\ncomment test\nelement vertex 4\nproperty float x\n"
        "property float y\nproperty float z\nproperty uchar red\nelement face 1\n"
        "property list uchar int vertex_indices\nelement edge 1\nproperty int vertex1\n"
        "property int vertex2\nend_header\n"
    )


def test_load_ply_ascii_and_binary_agree(tmp_path: Path) -> None:
    verts = [(0, 0, 0), (10, 0, 0), (10, 5, 0), (0, 5, 1.5)]
    body = "".join(f"{x} {y} {z} 7\n" for x, y, z in verts) + "4 0 1 2 3\n0 2\n"
    (tmp_path / "a.ply").write_text(ply_header("ascii") + body)
    raw = b"".join(struct.pack("<fffB", *v, 7) for v in verts)
    raw += struct.pack("<B4i", 4, 0, 1, 2, 3) + struct.pack("<2i", 0, 2)
    (tmp_path / "b.ply").write_bytes(ply_header("binary_little_endian").encode() + raw)
    a, b = load_ply(tmp_path / "a.ply"), load_model(tmp_path / "b.ply")
    np.testing.assert_allclose(a.vertices, verts)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.edges, b.edges)
    assert len(a.edges) == 5  # four outline edges plus the explicit diagonal
    assert a.faces.shape == (2, 3)


def test_manipulator_model_shape() -> None:
    m = manipulator_wireframe()
    assert 100 <= len(m.edges) <= 600
    assert m.vertices.dtype == np.float64
    assert m.edges.max() < len(m.vertices)
    assert m.vertices[:, 2].min() == 0.0  # stands on the floor
