"""ChArUco boards rendered by the synthetic camera, found by OpenCV's detector; frame stamps."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hil_sim.camera import FrameClock, PlacedBoard, SyntheticCamera
from host.calibration.board import MAX_EDGE_WIDTH_PX, BoardDetector, BoardSpec
from host.calibration.intrinsics import BASE_KEYS, calibrate_with_rejection
from host.geometry.camera import CameraModel
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import euler_zyx, invert_T, make_T

SPEC = BoardSpec()


def facing(
    spec: BoardSpec, angles: tuple[float, float, float], centre_mm: list[float]
) -> np.ndarray:
    """T_c_b with the board's centre at centre_mm in the camera frame."""
    R = euler_zyx(*angles)
    return make_T(R, np.array(centre_mm) - R @ spec.centre_mm)


@pytest.mark.parametrize(
    ("angles", "centre"),
    [
        ((0.1, 0.0, 0.2), [0, 0, 3000]),
        ((0.0, 0.6, -0.5), [150, -100, 2600]),
        ((0.2, -0.5, 0.4), [400, 250, 3800]),
    ],
)
def test_charuco_corners_found_where_the_true_lens_puts_them(angles, centre) -> None:  # type: ignore[no-untyped-def]
    det = BoardDetector(SPEC)
    sim = SyntheticCamera(CameraModel(), seed=2)  # Table 1: skew 0.263, k1 1.30, k2 1.88
    frame = sim.render_board(facing(SPEC, angles, centre), det.board)
    found = det.detect(frame.image)
    assert found is not None
    assert found.count >= 0.8 * frame.in_view.sum()
    err = np.abs(found.image_points - frame.corners_uv[found.ids])
    assert err.max() < 0.3
    assert found.sharp


def test_motion_blur_is_measured_and_refused() -> None:
    det = BoardDetector(SPEC)
    sim = SyntheticCamera(CameraModel(), seed=3)
    start = facing(SPEC, (0.1, 0.3, 0.2), [0, 0, 3000])
    end = start.copy()
    end[0, 3] += 4.0 * 3000 / 3676  # 4 px of motion during the exposure
    blurred = det.detect(sim.render_board(start, det.board, end).image)
    sharp = det.detect(sim.render_board(start, det.board).image)
    assert sharp is not None
    assert sharp.edge_width_px < MAX_EDGE_WIDTH_PX
    assert blurred is None or not blurred.sharp


def test_board_in_the_hall_behind_the_model() -> None:
    det = BoardDetector(SPEC)
    sim = SyntheticCamera(CameraModel(), seed=4)
    T_w_c = make_T(np.eye(3), [0.0, 0.0, -3000.0])
    T_c_b = facing(SPEC, (0.0, 0.2, 0.0), [0, 0, 3000])
    placed = PlacedBoard(det.board, T_w_c @ T_c_b)
    model_far = make_T(np.eye(3), [5000.0, 0.0, 0.0])  # the model off to the side
    frame = sim.render_scene(T_w_c, manipulator_wireframe(), model_far, board=placed)
    found = det.detect(frame.image)
    assert found is not None
    assert found.count == SPEC.corner_count
    assert invert_T(T_w_c) @ placed.T_w_b == pytest.approx(T_c_b)


def test_a_model_outside_the_field_of_view_is_not_folded_into_the_image() -> None:
    """Radial distortion with k2 < 0 turns back beyond some radius: the polynomial maps points
    far outside the lens's field of view into the image (the open gantry's seed-1 lens put the
    workpiece's edges across the board that way). A lens shows nothing from out there."""
    lens = CameraModel(fx=2850.0, fy=2850.0, skew=0.0, u0=960.0, v0=600.0, k1=-0.0226, k2=-0.312,
                       width=1920, height=1200)  # fmt: skip
    T_w_p = make_T(np.eye(3), [3900.0, 0.0, 3000.0])  # 50-55° off the axis, the camera at 0
    model = manipulator_wireframe()
    assert lens.one_to_one_radius() == pytest.approx(0.882, abs=1e-3)
    a, b = model.vertices[model.edges[:, 0]], model.vertices[model.edges[:, 1]]
    f = np.linspace(0.0, 1.0, 9)[None, :, None]
    uv, _ = lens.project((a[:, None] + f * (b - a)[:, None]).reshape(-1, 3) + T_w_p[:3, 3])
    inside = (uv[:, 0] > 0) & (uv[:, 0] < lens.width) & (uv[:, 1] > 0) & (uv[:, 1] < lens.height)
    assert inside.any()  # the premise: the polynomial puts some of the model in the image
    away = make_T(np.eye(3), [0.0, 0.0, -1e6])  # behind the camera
    shown = SyntheticCamera(lens, seed=2).render_scene(np.eye(4), model, T_w_p).image
    empty = SyntheticCamera(lens, seed=2).render_scene(np.eye(4), model, away).image
    np.testing.assert_array_equal(shown, empty)
    assert CameraModel(k1=-0.2, k2=0.1).one_to_one_radius() == math.inf  # monotonic: no limit


def test_frames_are_stamped_at_delivery_unless_triggered() -> None:
    free = FrameClock(seed=1)
    late_ns = np.array([free.stamp_ns(1_000_000_000) - 1_000_000_000 for _ in range(200)])
    assert late_ns.min() >= free.delivery_s * 1e9
    assert 0.0 < late_ns.std() < 3e6
    assert FrameClock(triggered=True).stamp_ns(123) == 123


def true_lens(rng: np.random.Generator) -> CameraModel:
    """A lens off Table 1 by manufacturing tolerances."""
    base = CameraModel()
    return dataclasses.replace(
        base,
        fx=base.fx * (1 + rng.normal(0, 0.01)), fy=base.fy * (1 + rng.normal(0, 0.01)),
        u0=base.u0 + rng.normal(0, 5), v0=base.v0 + rng.normal(0, 5),
        skew=base.skew + rng.normal(0, 0.3), k1=base.k1 + rng.normal(0, 0.1),
        k2=base.k2 + rng.normal(0, 0.3),
    )  # fmt: skip


@pytest.mark.parametrize("seed", [0, pytest.param(1, marks=pytest.mark.slow)])
def test_intrinsics_with_skew_recovered_within_three_reported_sigma(seed: int) -> None:
    rng = np.random.default_rng(seed)
    truth = true_lens(rng)
    det = BoardDetector(SPEC)
    sim = SyntheticCamera(truth, seed=seed)
    obj, img = [], []
    for _ in range(20):
        angles = tuple(rng.uniform([-0.3, -0.6, -0.6], [0.3, 0.6, 0.6]))
        centre = [rng.uniform(-250, 250), rng.uniform(-200, 200), rng.uniform(2600, 4000)]
        found = det.detect(sim.render_board(facing(SPEC, angles, centre), det.board).image)
        if found is not None:
            obj.append(found.object_points)
            img.append(found.image_points)
    res = calibrate_with_rejection(obj, img, truth.size)
    for key in BASE_KEYS:
        err = getattr(res.camera, key) - getattr(truth, key)
        assert abs(err) < 3.0 * res.std[key], (key, err, res.std[key])
    assert res.std["skew"] < 0.2  # the skew is resolved, not just carried
    assert res.rms_px < 0.1
