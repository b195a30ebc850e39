"""Per-frame registration against the simulator's rendered ground truth."""

from __future__ import annotations

import numpy as np

from hil_sim.camera import SyntheticCamera
from host.frames.registrar import Registrar
from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import invert_T, make_T, transform_points
from host.registration.pose_buffer import LookupStatus, PoseSource, SampleBuffer

MS = 1_000_000
SPEED_MM_PER_NS = 100.0 / 1e9  # 0.1 m/s


def _setup() -> tuple[Registrar, Rig, CameraModel, np.ndarray]:
    rig = Rig()
    camera = CameraModel()
    model = manipulator_wireframe()
    s_view, pan, tilt = 1500.0, 0.0, 0.0
    T_w_c = rig.T_w_c(s_view, pan, tilt)
    # Stand the workpiece 3 m in front of the camera, on its optical axis.
    T_w_p = make_T(np.eye(3), transform_points(T_w_c, np.array([[0.0, 0.0, 3000.0]]))[0])
    encoder = SampleBuffer(1)
    for k in range(50):
        encoder.push(k * MS, [s_view - 2.5 + k * MS * SPEED_MM_PER_NS])
    poses = PoseSource(rig, encoder, fixed_pan_rad=pan, fixed_tilt_rad=tilt)
    return Registrar(poses, camera, model, lambda _t: T_w_p), rig, camera, T_w_p


def test_centre_matches_the_true_projection_when_the_pose_is_exact() -> None:
    reg, rig, camera, T_w_p = _setup()
    t = 25 * MS
    s_true = 1500.0 - 2.5 + t * SPEED_MM_PER_NS
    T_w_c = rig.T_w_c(s_true, 0.0, 0.0)
    scene = SyntheticCamera(camera, seed=1).render_scene(T_w_c, reg.model, T_w_p)
    result = reg(Frame(1, scene.image, t))
    assert result.status is LookupStatus.OK
    assert result.centre_uv is not None
    centroid_c = transform_points(invert_T(T_w_c) @ T_w_p, reg.model.vertices.mean(0)[None])
    truth_uv, _ = camera.project(centroid_c)
    np.testing.assert_allclose(result.centre_uv, truth_uv[0], atol=1e-6)
    assert result.segments > 50
    assert result.image is not None
    assert not np.array_equal(result.image, scene.image)  # the overlay was drawn


def test_a_frame_past_the_buffer_horizon_gets_no_overlay() -> None:
    reg, *_ = _setup()
    result = reg(Frame(2, np.zeros((4, 4, 3), np.uint8), 10_000 * MS))
    assert result.status is LookupStatus.STALE
    assert result.centre_uv is None
    assert result.image is None
