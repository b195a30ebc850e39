"""`orbitar demo --rig FILE` end to end on a custom open track: simulator and host on one file."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_sim.camera import SyntheticCamera
from hil_sim.scenario import Scenario
from host.calibration.board import BoardDetector
from host.demo.commissioning_phase import board_view_conflicts, place_board
from host.demo.experiments import HOME_SURVEY_SAMPLES, Plan
from host.demo.rigs import DemoRigs, exact, model_of
from host.demo.run import run_demo
from host.rig import INTRINSIC_KEYS, build_kinematics, load_rig
from tests.demo.test_demo_quick import _static_bound_mm

RIGS = Path(__file__).resolve().parents[2] / "docs" / "rigs"
GANTRY = RIGS / "open-gantry.toml"
LOOP = RIGS / "stage-loop.toml"
SHORT = Plan(
    observation_mm=(0.0, 300.0),
    observations=4,
    travel_speed_mm_s=500.0,
    moving_length_mm=200.0,
    moving_speed_mm_s=300.0,
    moving_samples=4,
    loop_length_mm=2_500.0,
    loop_speed_mm_s=500.0,
    skips_at_fraction=(0.5,),
)


@pytest.fixture(scope="module")
def gantry(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    out = tmp_path_factory.mktemp("gantry")
    return asyncio.run(run_demo("pty", True, out, seed=3, rig_path=GANTRY, plan=SHORT)), out


def test_the_example_rig_is_an_open_track_of_straights_and_an_arc() -> None:
    track = build_kinematics(load_rig(GANTRY)).track
    assert not track.closed
    assert track.length_mm == pytest.approx(4000.0 + 1200.0 * 3.141592653589793 / 2)


def test_open_track_demo_registers_within_what_the_sensors_allow(
    gantry: tuple[dict[str, Any], Path],
) -> None:
    results, out = gantry
    assert results["rig"] == load_rig(GANTRY).name
    assert results["mode"] == {"tolerances": False, "commissioned": False}
    for row in results["static"].values():
        assert row["offset_mm"]["n"] == SHORT.observations
        assert row["offset_mm"]["max"] < _static_bound_mm()
    timing_mm = SHORT.moving_speed_mm_s * 2e-3
    assert results["moving"]["samples"] == SHORT.moving_samples
    bound = 100 * (_static_bound_mm() + timing_mm) / SHORT.moving_length_mm
    assert results["moving"]["R_percent"] < bound
    drift = results["drift"]
    assert drift["marks_seen"] >= 2
    # A frame exposed between the skip and its first fix carries a whole pitch (scored at the
    # workpiece's depth: ~27 px on this gantry), so the short loop's RMS depends on whether a
    # frame lands there: the skip is bounded by its frames, the rest by the encoder-only drift.
    assert max(drift["skip_frames"]) <= 2
    assert drift["fused_px_outside_skip_windows"]["rms"] < drift["encoder_only_px"]["rms"] / 10
    # The host was handed this very rig: every parameter's error is zero, but for the zero the
    # rangefinder surveyed (3 σ of its averaged readings).
    calibration = dict(results["calibration"])
    home = calibration.pop("track.home_mm")
    survey_mm = 3 * Scenario().rangefinder.noise_mm / math.sqrt(HOME_SURVEY_SAMPLES)
    assert abs(home["truth"] - home["estimate"]) < survey_mm
    assert all(abs(p.get("error_local", p["truth"] - p["estimate"])) < 1e-6
               for p in calibration.values())  # fmt: skip
    written = json.loads((out / "results.json").read_text())
    assert written["rig"] == results["rig"]
    assert load_rig(out / "rig.toml") == exact(load_rig(GANTRY))  # what the host read: σ 0


@pytest.mark.parametrize(
    "path",
    [
        pytest.param(GANTRY, id="open-gantry"),
        pytest.param(LOOP, id="stage-loop", marks=pytest.mark.slow),
    ],
)
def test_the_board_is_placed_for_the_rigs_lens_clear_of_its_workpiece(path: Path) -> None:
    """The open gantry's workpiece lay behind a board placed by the paper's rule: its edges,
    drawn over the board, left no corners at the board's own station. The board now goes where
    the drawing's workpiece crosses none of its views, at a distance (or print size) that lets
    the image's shorter side hold it, and the simulated camera finds it there."""
    rigs = DemoRigs.make(path, seed=1, tolerances=True)
    setup = place_board(rigs, 1)
    rig, camera = rigs.host_kinematics(), rigs.host_camera()
    conflicts = board_view_conflicts(rigs, rig, camera, setup.board, setup.placed.T_w_b, setup.s_mm)
    assert conflicts == (0, 0)  # no view spoilt by the workpiece, every view within the limits
    centre = (setup.placed.T_w_b @ np.append(setup.board.centre_mm, 1.0))[:3]
    pan, tilt = rigs.true_kinematics().aim(setup.s_mm, centre)
    T_w_c = rigs.true_kinematics().T_w_c(setup.s_mm, pan, tilt)
    image = (
        SyntheticCamera(rigs.true_camera(), seed=1)
        .render_scene(T_w_c, model_of(rigs.truth), rigs.true_workpiece(), board=setup.placed)
        .image
    )
    found = BoardDetector(setup.board).detect(image)
    assert found is not None
    assert found.sharp
    # all of it in view and readable (the detector may miss one corner at the edge: it does so
    # on the stage loop's lens with the workpiece removed too)
    assert found.count >= setup.board.corner_count - 2


@pytest.mark.slow
def test_open_track_commissions_through_the_daemon_and_registers_within_its_bounds(
    tmp_path: Path,
) -> None:
    """`orbitar demo --rig docs/rigs/open-gantry.toml --tolerances on` end to end: the host starts
    from the file's nominal values, commissions the seeded true rig through the daemon, and the
    experiments on the calibrated rig stay within the static bound. About 2-3 minutes."""
    results = asyncio.run(
        run_demo("pty", True, tmp_path, 1, GANTRY, tolerances=True, commission=True, plan=SHORT)
    )
    assert results["commissioning"]["passed"], results["commissioning"]
    assert results["mode"] == {"tolerances": True, "commissioned": True}
    for row in results["static"].values():
        assert row["offset_mm"]["max"] < _static_bound_mm()
    for key in INTRINSIC_KEYS:
        row = results["calibration"][f"camera.{key}"]
        assert abs(row["truth"] - row["estimate"]) <= 3 * row["sigma"] + 1e-12, (key, row)
