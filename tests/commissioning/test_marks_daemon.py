"""`survey_marks` and `calibrate_rangefinder` through the daemon's control socket (fake
controller, the true rig's mark sensor and rangefinder): what is written, and what is not."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np

from host.commissioning.client import run_op
from host.rig import load_rig
from tests.commissioning.rangefinder_truth import draw_truth, hall_rig, sensed_daemon

HOME_MM = 150.0
MARKS = (400.0, 650.0, 900.0)
CALIBRATED = {"mount_sigma": (0.5, 5e-4), "placement_sigma": (0.5, 3e-4)}


async def test_a_marks_survey_through_the_daemon_writes_marks_within_their_sigma(
    tmp_path: Path,
) -> None:
    spec = hall_rig(**CALIBRATED, marks_mm=MARKS)
    truth = draw_truth(spec, np.random.default_rng(21), mount_from_spec=True)
    async with sensed_daemon(tmp_path, spec, truth, HOME_MM, 21) as bench:
        result = await run_op(
            bench.client, "survey_marks", {"samples": 10, "cross_speed_mm_s": 250.0}
        )
    assert result["passed"], result["reasons"]
    assert result["written"] == str(bench.rig_path)
    assert Path(result["report"]).is_file()
    marks = load_rig(bench.rig_path).track.marks
    assert marks.provenance.method.startswith("survey marks")
    for got, true, each in zip(marks.s_mm, truth.marks_mm, result["marks"], strict=True):
        assert abs(got - true) < 3 * each["sigma_mm"], (got, true, each["sigma_mm"])
        assert each["sigma_mm"] <= marks.sigma_mm


async def test_an_interrupted_marks_survey_leaves_the_rig_file_alone(tmp_path: Path) -> None:
    spec = hall_rig(**CALIBRATED, marks_mm=MARKS)
    truth = draw_truth(spec, np.random.default_rng(22), mount_from_spec=True)
    async with sensed_daemon(tmp_path, spec, truth, HOME_MM, 22) as bench:
        before = bench.rig_path.read_bytes()
        started = await bench.client.request("survey_marks")
        for _ in range(100):
            status = await bench.client.request("commissioning_status", job=started["job"])
            if status.get("progress", {}).get("view", 0) >= 2:
                break
            await asyncio.sleep(0.05)
        assert (await bench.client.request("commissioning_cancel"))["cancelled"]
        status = await bench.client.request("commissioning_status", job=started["job"])
    assert status["state"] == "cancelled"
    assert bench.rig_path.read_bytes() == before


async def test_a_degenerate_mount_calibration_fails_and_writes_nothing(tmp_path: Path) -> None:
    spec = hall_rig(marks_mm=MARKS)
    truth = draw_truth(spec, np.random.default_rng(23))
    async with sensed_daemon(tmp_path, spec, truth, HOME_MM, 23) as bench:
        before = bench.rig_path.read_bytes()
        one_pose = [[HOME_MM, 0.4, 1.0]] * 3  # where the trolley stands after homing
        result = await run_op(
            bench.client, "calibrate_rangefinder", {"aims": one_pose, "samples": 3}
        )
    assert not result["passed"]
    assert "all readings come from one pose" in result["reasons"][0]
    assert result["written"] is None
    assert Path(result["report"]).is_file()
    assert bench.rig_path.read_bytes() == before
