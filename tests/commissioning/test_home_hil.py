"""HIL: `survey_home` through the real daemon on the simulator (no camera needed).

The shared HIL rig (tests.hil_rig): `orbitar daemon` as a process on the emulator's pty, the
emulator (tests.attack.rogue_sim, which writes its truth to a file) simulating the demo's rig
with seeded installation tolerances; the plant's rangefinder reaches the daemon over the link.
The daemon knows the rig file only. After homing, the beam is aimed back along the track at
the hall's surveyed end wall and the survey finds where the controller's zero lies on the
track; the emulator's truth is used only in the assertion.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np
import pytest

from host.commissioning.client import CommissioningPlan, commission
from host.control.client import ControlClient
from host.demo.rigs import DemoRigs
from host.geometry.head import Rig as Kinematics
from host.rig import load_rig, save_rig
from host.rig.build import build_scene
from tests.attack.rig import Rig
from tests.hil_rig import Rigs

SEED = 5
ALONG_MM = 300.0  # the survey's station past the zero
READY_TIMEOUT_S = 40.0


class DemoRig(Rig):
    """The emulator simulating the rig file with seeded tolerances, writing its truth."""

    seed = SEED

    def sim_args(self) -> list[str]:
        return [
            "--link", "pty", "--link-path", str(self.dir / "sim"), "--rig", str(self.rig_path),
            "--tolerances", "--seed", str(self.seed), "--truth", str(self.dir / "truth.json"),
        ]  # fmt: skip


async def until_at_rest(socket_path: str, homed: bool) -> None:
    """Until a published pose says READY (with the zero referenced, if `homed`).

    Poses, not `status`: a status computes the error budget on the daemon's loop, and polled
    on a loaded machine it delays the heartbeats past the controller's watchdog.
    """
    async with await ControlClient.connect_unix(socket_path) as client:
        await client.request("subscribe", topics=["pose"])
        deadline = time.monotonic() + READY_TIMEOUT_S
        pose: dict[str, Any] = {}
        while time.monotonic() < deadline:
            event = await client.next_event(timeout_s=READY_TIMEOUT_S)
            if event["topic"] == "pose":
                pose = event["data"]
                if pose["state"] == "READY" and (pose["homed"] or not homed):
                    return
    raise AssertionError(f"not at rest{' homed' if homed else ''} in {READY_TIMEOUT_S} s: {pose}")


async def test_survey_home_on_the_simulator_through_the_real_daemon(hil_rig: Rigs) -> None:
    rigs = DemoRigs.make(None, SEED, tolerances=True)
    rig = hil_rig(DemoRig)
    save_rig(rigs.nominal, rig.rig_path)  # the emulator adds the tolerances, the host never
    await asyncio.to_thread(rig.start)
    # The installer aims by the rig file: back along the track, level, at the surveyed wall.
    host = rigs.host_kinematics()
    beam = Kinematics(track=host.track, T_r_c=host.T_r_l)
    walls = build_scene(rigs.nominal)
    assert walls is not None
    async with await ControlClient.connect_unix(rig.socket_path) as client:
        await client.request("home")
        await asyncio.sleep(0.5)  # HOMING by now
        await until_at_rest(rig.socket_path, homed=True)
        await client.request("move", position_mm=ALONG_MM, speed_mm_s=500.0)
        await asyncio.sleep(0.5)  # MOVING by now
        await until_at_rest(rig.socket_path, homed=True)
        s_mm = ALONG_MM + load_rig(rig.rig_path).track.home.value
        T = host.track.pose(s_mm)
        back = -T[:3, 0] * np.array([1.0, 1.0, 0.0])
        back /= np.linalg.norm(back)
        hit = walls.cast(T[:3, 3], back)
        assert hit is not None
        pan, tilt = beam.aim(s_mm, T[:3, 3] + hit.distance_mm * back)
        plan = CommissioningPlan().add("survey_home", pan_rad=pan, tilt_rad=tilt)
        [(_, result)] = await commission(client, plan)
    zero_mm = rig.truth_zero_mm()
    assert result["passed"], result["reasons"]
    err_mm = result["home_mm"] - zero_mm
    assert abs(err_mm) < 3.0 * result["sigma_mm"], (err_mm, result["sigma_mm"])
    assert load_rig(rig.rig_path).track.home.value == pytest.approx(result["home_mm"])
