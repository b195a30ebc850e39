"""The demo's commissioning session: the board and surveys it sets up, and (slow) the whole run."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest

from host.demo.commissioning_phase import (
    BOARD,
    BOARD_SURVEY_SIGMA_MM,
    commissioning_plan,
    place_board,
)
from host.demo.rigs import DemoRigs
from host.demo.run import run_demo
from host.geometry.transforms import invert_T
from host.rig import INTRINSIC_KEYS, load_rig


def test_board_is_under_the_track_and_its_survey_is_off_by_about_its_sigma() -> None:
    rigs = DemoRigs.make(None, seed=4, tolerances=True)
    a, b = place_board(rigs, 4), place_board(rigs, 4)
    np.testing.assert_array_equal(a.placed.T_w_b, b.placed.T_w_b)  # seeded
    centre = (a.placed.T_w_b @ np.append(BOARD.centre_mm, 1.0))[:3]
    above = rigs.host_kinematics().track.position(a.s_mm)
    assert np.hypot(*(centre - above)[:2]) < 600.0
    assert 1000.0 < above[2] - centre[2] < 3000.0
    assert a.placed.T_w_b[2, 2] < -0.9  # face up: the board's z points down into the floor
    off = invert_T(a.placed.T_w_b) @ a.T_w_b_surveyed
    assert 0.0 < np.linalg.norm(off[:3, 3]) < 5 * BOARD_SURVEY_SIGMA_MM
    lo, hi = rigs.travel_mm()
    steps = commissioning_plan(rigs, a).steps
    for _, args in steps:
        where = [
            *args.get("stations_mm", []),
            *([args["station_mm"]] if "station_mm" in args else []),
        ]
        assert all(lo < s < hi for s in where)
    ops = [op for op, _ in steps]
    assert ops[0] == "survey_home"  # the zero first: every later step drives in arc length
    assert ops.index("calibrate_head") < ops.index("survey_workpiece")  # through the rig
    assert "calibrate_latency" in ops


@pytest.mark.slow
def test_commissioned_demo_recovers_the_true_lens_within_its_sigma(tmp_path: Path) -> None:
    results = asyncio.run(run_demo("pty", True, tmp_path, seed=3, tolerances=True, commission=True))
    assert results["commissioning"]["passed"], results["commissioning"]
    assert results["mode"]["commissioned"]
    rig = load_rig(tmp_path / "rig.toml")
    assert rig.camera.intrinsics.provenance.method != "nominal"
    assert rig.head.m_cr.provenance.method != "nominal"
    for key in INTRINSIC_KEYS:
        row = results["calibration"][f"camera.{key}"]
        assert abs(row["truth"] - row["estimate"]) <= 3 * row["sigma"] + 1e-12, (key, row)
    measured = ("camera.", "head.m_cr", "track.placement", "track.home", "workpiece.frame")
    for key, row in results["calibration"].items():
        if key.startswith(measured) and row["sigma"] > 0:  # a calibration reports what it achieves
            error = row.get("error_local", row["estimate"] - row["truth"])
            assert abs(error) <= 3 * row["sigma"], (key, row)
    assert rig.workpiece.frame.provenance.method.startswith("survey workpiece (camera")
    assert rig.track.home.provenance.method.startswith("survey home (rangefinder")
