"""`orbitar demo --rig FILE` end to end on a custom open track: simulator and host on one file."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path
from typing import Any

import pytest

from hil_sim.scenario import Scenario
from host.demo.experiments import HOME_SURVEY_SAMPLES, Plan
from host.demo.run import run_demo
from host.rig import build_kinematics, load_rig
from tests.demo.test_demo_quick import _static_bound_mm

GANTRY = Path(__file__).resolve().parents[2] / "docs" / "rigs" / "open-gantry.toml"
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
    assert drift["fused_px"]["rms"] < drift["encoder_only_px"]["rms"] / 10
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
    assert load_rig(out / "rig.toml") == load_rig(GANTRY)  # what the host read
