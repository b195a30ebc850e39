"""Commissioning on the simulator through the daemon's own wiring: firmware mirror, plant, pty link.

The daemon is started as the demo starts it (host.demo.daemon_phase.running_daemon: the real
controller factory and frame loop, `[rig] path` on a nominal rig file); its camera renders a
board in the hall through the simulator's true rig and lens (seeded tolerances) and stamps
frames at delivery. Nothing of the truth reaches the daemon.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_sim.camera import FrameClock, PlacedBoard, SyntheticCamera
from host.commissioning.client import CommissioningPlan, commission
from host.control.client import ControlClient
from host.demo.daemon_phase import running_daemon
from host.demo.rigs import DemoRigs
from host.demo.world import SimWorld
from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.rig import load_rig, save_rig
from tests.commissioning.simrig import BOARD, BOARD_CENTRE_W, board_pose

KEYS = ("fx", "fy", "skew", "u0", "v0", "k1", "k2")
FPS = 10.0


class BoardCamera:
    """A FrameSource rendering the board at the plant's true pose (true rig, true lens)."""

    def __init__(self, world: SimWorld, rig: Rig, lens: CameraModel, board: PlacedBoard, seed: int):
        self.world, self.rig, self.board = world, rig, board
        self.cam = SyntheticCamera(lens, seed=seed)
        self.clock = FrameClock(seed=seed)
        self._closed = threading.Event()
        self._index = 0

    def read(self) -> Frame | None:
        if self._closed.wait(1.0 / FPS):
            return None
        truth = self.world.with_truth(lambda sim: sim.truth())
        exposure_ns = self.world.host_time_ns(truth.time_s)
        T_w_c = self.rig.T_w_c(truth.s_wrapped_mm, truth.pan_rad, truth.tilt_rad)
        image = self.cam.render_board(
            np.linalg.inv(T_w_c) @ self.board.T_w_b, self.board.board
        ).image
        stamp = self.clock.stamp_ns(exposure_ns)
        time.sleep(max(0.0, (stamp - time.monotonic_ns()) / 1e9))
        self._index += 1
        return Frame(self._index, image, stamp, None)

    def close(self) -> None:
        self._closed.set()


async def _until(
    client: ControlClient, ok: Callable[[Any], Any], what: str, timeout_s: float = 90.0
) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = await client.request("status")
        if ok(status):
            return status
        await asyncio.sleep(0.2)
    raise AssertionError(f"{what}: not within {timeout_s} s")


@pytest.mark.slow
async def test_intrinsics_on_the_simulator_through_the_real_daemon(tmp_path: Path) -> None:
    seed = 3
    rigs = DemoRigs.make(None, seed, tolerances=True)
    rig_file = tmp_path / "rig.toml"
    save_rig(rigs.nominal, rig_file)
    world = SimWorld(rigs.scenario(seed), "pty")
    board = PlacedBoard(BOARD.make(), board_pose(np.random.default_rng(seed)))
    camera = BoardCamera(world, rigs.true_kinematics(), rigs.true_camera(), board, seed)
    await world.start()
    try:
        async with running_daemon(world, rig_file, tmp_path / "daemon", camera=camera) as d:
            client = await ControlClient.connect_unix(str(d.socket_path))
            async with client:
                await _until(client, lambda s: s.get("link_up"), "link up")
                await client.request("home")
                await _until(client, lambda s: s["controller"].get("state") == "READY", "homed")
                centre = [float(x) + 30.0 for x in BOARD_CENTRE_W]
                plan = CommissioningPlan().intrinsics(
                    centre, [700.0, 1700.0, 2700.0], board=BOARD.to_dict()
                )
                [(_, result)] = await commission(client, plan)
    finally:
        await world.stop()
    assert result["passed"], result["reasons"]
    truth = rigs.true_camera()
    for key in KEYS:
        err = result["camera"][key] - getattr(truth, key)
        assert abs(err) < 3.0 * result["sigma"][key], (key, err, result["sigma"][key])
    assert load_rig(rig_file).camera.intrinsics.get("fx") == pytest.approx(result["camera"]["fx"])
