"""The drift loop's score: the workpiece overlay an operator sees, not the world frame's error."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from host.demo.rigs import paper_demo_rig
from host.demo.scoring import aimed_errors, workpiece_errors
from host.demo.world import SceneTruth
from host.frames.registrar import Registration
from host.geometry.transforms import make_T, rotvec_to_R
from host.registration.pose_buffer import LookupStatus
from host.rig import build_camera, build_kinematics

SPEC = paper_demo_rig()
RIG, CAMERA = build_kinematics(SPEC), build_camera(SPEC)
POINT_W = np.array([-300.0, -300.0, 500.0])
S_MM, AHEAD = 2500.0, (0.0, np.pi / 2)  # the loop looks along the track, not at the workpiece


def _registration(s_mm: float) -> Registration:
    return Registration(0, 0, LookupStatus.OK, np.eye(4), s_mm, *AHEAD, None, 0, None, None)


def _truth() -> SceneTruth:
    return SceneTruth(RIG.T_w_c(S_MM, *AHEAD), np.eye(4), S_MM, *AHEAD)


def test_a_world_frame_error_the_surveyed_workpiece_shares_does_not_show() -> None:
    """The track placed 1 mrad and 2 mm off (the board's survey): the workpiece, surveyed through
    the same rig, is placed off by the same transform, so its overlay is right."""
    off = make_T(rotvec_to_R([0.0, 1e-3, 1e-3]), [2.0, 0.0, 0.0])
    host = dataclasses.replace(RIG, track=RIG.track.with_origin(off @ RIG.track.T_w_track))
    host_point = (off @ np.append(POINT_W, 1.0))[:3]
    reg = (_registration(S_MM),)
    seen = workpiece_errors(reg, _truth(), (host, CAMERA), (RIG, CAMERA), (host_point, POINT_W))
    assert seen[0].error_px < 1e-6
    world = aimed_errors(reg, _truth(), (host, CAMERA), (RIG, CAMERA), POINT_W)
    assert world[0].error_px > 2.0  # a probe on the axis counts it: ~1 mrad × fx


def test_a_track_position_error_shows_at_the_workpieces_depth() -> None:
    delta_mm = 1.0
    reg = (_registration(S_MM + delta_mm),)
    got = workpiece_errors(reg, _truth(), (RIG, CAMERA), (RIG, CAMERA), (POINT_W, POINT_W))[0]
    T_w_c = RIG.T_w_c(S_MM, *RIG.aim(S_MM, POINT_W))  # aimed at the point: it is on the axis
    view = T_w_c[:3, :3].T @ RIG.track.pose(S_MM)[:3, 0]  # the track's direction, camera frame
    depth = float(np.linalg.norm(POINT_W - T_w_c[:3, 3]))
    across = float(np.linalg.norm(view[:2]))  # the part of the move the image can see
    assert got.error_px == pytest.approx(CAMERA.fx * delta_mm * across / depth, rel=0.05)
    assert got.error_mm == pytest.approx(delta_mm * across, rel=0.05)
