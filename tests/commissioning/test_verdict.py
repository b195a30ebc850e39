"""The intrinsics verdict on captured views: too few, degenerate and blurred sets fail clearly."""

from __future__ import annotations

import numpy as np
import pytest

from hil_sim.camera import SyntheticCamera
from host.calibration.board import BoardDetector
from host.commissioning import coverage
from host.commissioning.intrinsics_run import CapturedView, Thresholds, judge, rig_update
from host.commissioning.plan import ViewTarget, board_plan
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import euler_zyx, make_T
from tests.commissioning.simrig import BOARD

NOMINAL = CameraModel()


def captured(poses: list[np.ndarray], blur_mm: float = 0.0) -> list[CapturedView]:
    """Views as the run would have kept them, rendered at the given board poses."""
    det = BoardDetector(BOARD)
    sim = SyntheticCamera(NOMINAL, seed=1, blur_samples=4)
    out = []
    for i, T in enumerate(poses):
        end = None
        if blur_mm:
            end = T.copy()
            end[0, 3] += blur_mm
        found = det.detect(sim.render_board(T, det.board, end).image)
        target = ViewTarget(0.0, 0.0, 0.0, f"view {i}")
        if found is None:
            out.append(CapturedView(target, "not found"))
            continue
        ok = found.sharp
        cover = (
            coverage.view_coverage(found.object_points, found.image_points, NOMINAL) if ok else None
        )
        out.append(CapturedView(target, "ok" if ok else "blurred", found, cover, 1))
    return out


def pose(angles: tuple[float, float, float], centre: list[float]) -> np.ndarray:
    R = euler_zyx(*angles)
    return make_T(R, np.array(centre) - R @ BOARD.centre_mm)


def test_the_same_view_twelve_times_is_degenerate_and_not_solved() -> None:
    views = captured([pose((0.1, 0.1, 0.1), [0, 0, 2600])] * 12)
    out = judge(views, NOMINAL, Thresholds())
    assert not out.passed
    assert out.result is None
    assert out.reasons[0].startswith("degenerate views")
    assert "skew coverage" in out.reasons[0]


def test_too_few_views_name_what_was_missing() -> None:
    views = captured([pose((0.1, 0.3, 0.1), [0, 0, 2600]), pose((0.0, -0.4, 0.2), [100, 50, 3000])])
    out = judge(views, NOMINAL, Thresholds())
    assert not out.passed
    assert (
        "too few views: 2 kept of 2 planned (0 blurred, 0 without the board), need ≥ 10"
        in out.reasons
    )


def test_blurred_views_are_counted_and_refused() -> None:
    views = captured([pose((0.1, 0.3, 0.1), [0, 0, 2600])] * 3, blur_mm=4.0)
    out = judge(views, NOMINAL, Thresholds(min_views=3))
    assert not out.passed
    assert "3 blurred" in out.reasons[0] or "3 without the board" in out.reasons[0]


def test_a_failed_verdict_has_nothing_to_write() -> None:
    out = judge([], NOMINAL, Thresholds())
    with pytest.raises(ValueError, match="only a passing calibration"):
        rig_update(out)


def test_the_plan_puts_the_board_where_it_aims() -> None:
    rig, centre = Rig(), np.array([-300.0, -1100.0, 1500.0])
    plan = board_plan(rig, NOMINAL, centre, [1700.0])
    assert len(plan) == 5
    for view, (fx, fy) in zip(
        plan, [(0.5, 0.5), (0.3, 0.3), (0.7, 0.3), (0.3, 0.7), (0.7, 0.7)], strict=True
    ):
        uv, _ = NOMINAL.project_world(
            rig.T_c_w(view.s_mm, view.pan_rad, view.tilt_rad), centre[None]
        )
        assert np.allclose(uv[0], [fx * 1279, fy * 1023], atol=1.0)
