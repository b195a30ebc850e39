"""`calibrate_intrinsics` through a running daemon: plan, capture, solve, verdict, rig file."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from host.commissioning.client import CommissioningPlan, commission, run_op
from host.rig import load_rig
from tests.commissioning.simrig import BOARD, BOARD_CENTRE_W, STATIONS_MM, sim_daemon

KEYS = ("fx", "fy", "skew", "u0", "v0", "k1", "k2")


def args(**extra: object) -> dict[str, object]:
    """The request an installer would send: rough board position, stations, the board."""
    centre = [float(x) + 30.0 for x in BOARD_CENTRE_W]  # a tape measure, 3 cm off
    return {
        "board_centre_mm": centre,
        "stations_mm": STATIONS_MM,
        "board": BOARD.to_dict(),
        **extra,
    }


async def test_intrinsics_through_the_daemon_pass_within_three_sigma_and_written(
    tmp_path: Path,
) -> None:
    async with sim_daemon(tmp_path, seed=5) as h:
        await h.request("home")
        seen: list[dict[str, object]] = []
        plan = CommissioningPlan().intrinsics(**args())  # type: ignore[arg-type]
        [(op, result)] = await commission(h.client, plan, seen.append)
    assert op == "calibrate_intrinsics"
    assert result["passed"], result["reasons"]
    assert any("coverage" in p for p in seen)
    for key in KEYS:
        err = result["camera"][key] - getattr(h.lens, key)
        assert abs(err) < 3.0 * result["sigma"][key], (key, err, result["sigma"][key])
    assert result["written"] == str(h.rig_path)
    intr = load_rig(h.rig_path).camera.intrinsics
    assert intr.get("fx") == pytest.approx(result["camera"]["fx"])
    assert intr.provenance.method.startswith("calibrate intrinsics")
    assert Path(result["report"]).exists()
    assert "PASS" in Path(result["report"]).read_text()


@pytest.mark.slow
async def test_blurred_views_fail_with_a_clear_message_and_write_nothing(tmp_path: Path) -> None:
    async with sim_daemon(tmp_path, seed=6, blur_mm=6.0) as h:
        before = h.rig_path.read_text()
        await h.request("home")
        result = await run_op(h.client, "calibrate_intrinsics", args(stations_mm=STATIONS_MM[:1]))
    assert not result["passed"]
    assert "too few views" in result["reasons"][0]
    assert "blurred" in result["reasons"][0]
    assert result["written"] is None
    assert h.rig_path.read_text() == before


async def test_stop_cancels_the_run_and_the_rig_file_is_untouched(tmp_path: Path) -> None:
    async with sim_daemon(tmp_path, seed=7) as h:
        before = h.rig_path.read_text()
        await h.request("home")
        started = await h.request("calibrate_intrinsics", **args())
        await asyncio.sleep(1.0)
        await h.request("stop")
        status = await h.request("commissioning_status", job=started["job"])
        for _ in range(50):
            if status["state"] != "running":
                break
            await asyncio.sleep(0.05)
            status = await h.request("commissioning_status", job=started["job"])
    assert status["state"] == "cancelled"
    assert status["reason"] == "STOP"
    assert h.rig_path.read_text() == before
