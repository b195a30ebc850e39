"""View plans within a head's limits: the other way round, and the pan taken modulo 2π."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.commissioning.ops import image_targets
from host.commissioning.plan import (
    IMAGE_TARGETS,
    aim_options,
    aim_within,
    board_plan,
    other_way,
    slew_rad,
)
from host.commissioning.targets_run import plan_views
from host.control.ops import OpError
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import transform_points

BOARD_W = np.array([-300.0, -1100.0, 1500.0])  # under the paper runway's first straight
STATIONS = [700.0, 1700.0, 2700.0]


def _centre_pixel(rig: Rig, camera: CameraModel, s: float, pan: float, tilt: float) -> np.ndarray:
    uv, ok = camera.project(transform_points(rig.T_c_w(s, pan, tilt), BOARD_W))
    assert bool(ok)
    return np.asarray(uv)


def test_a_head_that_tilts_one_way_only_is_aimed_the_other_way_round() -> None:
    rig, camera = Rig(), CameraModel()
    free = board_plan(rig, camera, BOARD_W, STATIONS)
    assert len(free) == len(STATIONS) * len(IMAGE_TARGETS)
    # The free plan tilts both ways; a head whose tilt stops at 0 on one side still gets every
    # view, by pan + π with the tilt mirrored.
    sides = {math.copysign(1.0, v.tilt_rad) for v in free}
    assert sides == {-1.0, 1.0}
    for side in (1.0, -1.0):
        tilt = (0.0, math.pi / 2) if side > 0 else (-math.pi / 2, 0.0)
        limits = ((-math.pi, math.pi), tilt)
        plan = board_plan(rig, camera, BOARD_W, STATIONS, limits=limits)
        assert len(plan) == len(free)
        size = np.array([camera.width - 1.0, camera.height - 1.0])
        for view, (fx, fy) in zip(plan, IMAGE_TARGETS * len(STATIONS), strict=True):
            assert tilt[0] <= view.tilt_rad <= tilt[1]
            uv = _centre_pixel(rig, camera, view.s_mm, view.pan_rad, view.tilt_rad)
            assert np.hypot(*(uv - size * np.array([fx, fy]))) < 5.0


def test_a_pan_is_taken_into_limits_that_do_not_straddle_zero() -> None:
    rig, camera = Rig(), CameraModel()
    assert any(v.pan_rad < 0.0 for v in board_plan(rig, camera, BOARD_W, STATIONS))
    limits = ((0.0, 2 * math.pi), (-math.pi / 2, math.pi / 2))
    plan = board_plan(rig, camera, BOARD_W, STATIONS, limits=limits)
    assert len(plan) == len(STATIONS) * len(IMAGE_TARGETS)
    assert all(0.0 <= v.pan_rad <= 2 * math.pi for v in plan)


def test_the_other_way_points_the_camera_along_the_same_axis() -> None:
    rig = Rig()
    s, pan, tilt = 1700.0, 0.4, -0.6
    axis = rig.T_w_c(s, pan, tilt)[:3, 2]
    pan2, tilt2 = other_way(rig, (pan, tilt))
    axis2 = rig.T_w_c(s, pan2, tilt2)[:3, 2]
    # M_cr turns the camera ~8° about its axis and tilts it a little: the second branch is a
    # start for Newton's method, within a few degrees of the same direction
    assert math.degrees(math.acos(float(np.clip(axis @ axis2, -1.0, 1.0)))) < 3.0


def test_with_near_a_view_takes_the_way_the_head_reaches_soonest() -> None:
    rig, camera = Rig(), CameraModel()
    size = np.array([camera.width - 1.0, camera.height - 1.0])
    uv = size * np.array([0.3, 0.7])
    first, other = aim_options(rig, camera, 1700.0, BOARD_W, uv, None)
    assert aim_within(rig, camera, 1700.0, BOARD_W, uv, None) == first  # Rig.aim's way
    for near in (first, other):
        assert aim_within(rig, camera, 1700.0, BOARD_W, uv, None, near) == near
    # the other way points the camera along the same axis, rolled: the point at the same pixel
    for pan, tilt in (first, other):
        assert np.hypot(*(_centre_pixel(rig, camera, 1700.0, pan, tilt) - uv)) < 5.0


def test_board_plans_take_rig_aims_way_so_their_views_tilt_both_ways() -> None:
    rig, camera = Rig(), CameraModel()
    size = np.array([camera.width - 1.0, camera.height - 1.0])
    plan = board_plan(rig, camera, BOARD_W, STATIONS)
    wanted = [(s, size * np.array(t)) for s in STATIONS for t in IMAGE_TARGETS]
    for view, (s, uv) in zip(plan, wanted, strict=True):
        assert (view.pan_rad, view.tilt_rad) == aim_options(rig, camera, s, BOARD_W, uv, None)[0]
    assert {math.copysign(1.0, v.tilt_rad) for v in plan} == {-1.0, 1.0}


def test_the_targets_plan_turns_the_head_the_nearer_way() -> None:
    rig, camera = Rig(), CameraModel()
    points_w = BOARD_W + np.array([[0.0, 0.0, 0.0], [300.0, 0.0, 0.0], [0.0, 200.0, 0.0]])
    plans = {}
    for start in ((math.pi / 2, 0.0), (-math.pi / 2, 0.0)):
        views = plan_views(rig, camera, points_w, STATIONS, None, start)
        assert sorted({k for v in views for k in v.wanted}) == [0, 1, 2]
        plans[start] = [(v.target.pan_rad, v.target.tilt_rad) for v in views]
    (a, first_a), (b, first_b) = ((s, p[0]) for s, p in plans.items())
    # each plan's first view is the way nearer its own start, the other plan's the other way
    assert slew_rad(a, first_a) < slew_rad(a, first_b)
    assert slew_rad(b, first_b) < slew_rad(b, first_a)


def test_image_targets_are_checked_before_anything_moves() -> None:
    assert image_targets({}) == IMAGE_TARGETS
    assert image_targets({"image_targets": [[0.5, 0.5], [0.3, 0.7]]}) == ((0.5, 0.5), (0.3, 0.7))
    for bad in ([], [[0.5]], [[0.0, 0.5]], [[0.5, 1.2]], [["a", 0.5]], "centre", [[0.5, 0.5]] * 26):
        with pytest.raises(OpError, match="image_targets"):
            image_targets({"image_targets": bad})
