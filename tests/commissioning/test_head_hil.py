"""HIL: head calibration and acceptance check through the real daemon on the emulator.

The emulator runs as a process of its own (tests.attack.rogue_sim: the firmware mirror and the
plant behind a pty, simulating the demo's rig file with seeded installation tolerances, its
truth in a file). The daemon's own code (`Daemon` with the real wiring) runs in the test's
process because its camera must: that camera renders the board, on its stand under the track,
through the true rig and lens at the plant's true pose (views are captured at rest, so the
truth file's 50 ms is fresh enough). The installer's session is the demo's: home, survey the
controller's zero (1 mm), `calibrate_intrinsics`, `calibrate_head`, `calibrate_check`. Truth
is used only by that camera, the survey's measurement and the assertions.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from hil_sim.camera import PlacedBoard, SyntheticCamera
from host.commissioning.client import commission
from host.config import loads_config
from host.control.client import ControlClient
from host.demo.commissioning_phase import commissioning_plan, place_board
from host.demo.rigs import DemoRigs
from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig as Kinematics
from host.geometry.transforms import R_to_rotvec
from host.rig import INTRINSIC_KEYS, Provenance, Scalar, load_rig, save_rig, update_rig
from host.rig.schema import SURVEY_SIGMA_MM
from host.service import wiring
from host.service.daemon import Daemon
from tests.attack.rig import Rig
from tests.commissioning.test_home_hil import DemoRig, until_at_rest
from tests.hil_rig import Rigs

SEED = 3
CAMERA_FPS = 4.0  # views are captured at rest: a slow camera loses nothing and leaves the CPU
POLL_S = 1.0  # `status` computes the error budget on the daemon's loop: not faster than this


class TruthCamera:
    """A FrameSource: the board as the true camera sees it at the emulator's true pose."""

    def __init__(self, rig: Rig, kinematics: Kinematics, lens: CameraModel, board: PlacedBoard):
        self.rig, self.kinematics, self.board = rig, kinematics, board
        self.cam = SyntheticCamera(lens, seed=SEED)
        self._closed = threading.Event()
        self._index = 0

    def read(self) -> Frame | None:
        if self._closed.wait(1.0 / CAMERA_FPS):
            return None
        exposed_ns = time.monotonic_ns()
        truth = self.rig.truth()
        T_w_c = self.kinematics.T_w_c(truth["s_wrapped_mm"], truth["pan_rad"], truth["tilt_rad"])
        T_c_b = np.linalg.inv(T_w_c) @ self.board.T_w_b
        self._index += 1
        return Frame(self._index, self.cam.render_board(T_c_b, self.board.board).image, exposed_ns)

    def close(self) -> None:
        self._closed.set()


def local_error(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """δ with truth = est · exp(δ): (rotation vector, translation), as the covariances are."""
    d = np.linalg.inv(est) @ truth
    return np.concatenate([R_to_rotvec(d[:3, :3]), d[:3, 3]])


class SeededDemoRig(DemoRig):
    seed = SEED


@pytest.mark.slow
async def test_head_and_check_through_the_real_daemon_on_the_emulator(hil_rig: Rigs) -> None:
    rigs = DemoRigs.make(None, SEED, tolerances=True)  # the emulator draws the same truth
    rig = hil_rig(SeededDemoRig)
    save_rig(rigs.nominal, rig.rig_path)
    await asyncio.to_thread(rig.start_sim)
    setup = place_board(rigs, SEED)
    camera = TruthCamera(rig, rigs.true_kinematics(), rigs.true_camera(), setup.placed)
    config = loads_config(rig.config.read_text())
    frames = functools.partial(wiring.frame_loop_factory, camera=camera)
    daemon = Daemon(config, wiring.controller_factory, frames, config_path=rig.config)
    task = asyncio.create_task(daemon.run())
    try:
        while not Path(rig.socket_path).exists():
            assert not task.done(), "the daemon stopped at start"
            await asyncio.sleep(0.05)
        async with await ControlClient.connect_unix(rig.socket_path) as client:
            while not (await client.request("status")).get("link_up"):
                await asyncio.sleep(POLL_S)
            await client.request("home")
            await asyncio.sleep(0.5)  # HOMING by now
            await until_at_rest(rig.socket_path, homed=True)
            await asyncio.sleep(0.5)  # the rotor rings down before the zero is surveyed
            # the installer's survey of the zero: the truth and a 1 mm tape's error
            noise = float(np.random.default_rng(SEED).normal(0.0, SURVEY_SIGMA_MM))
            zero = Scalar(rig.truth_zero_mm() + noise, SURVEY_SIGMA_MM, Provenance.now("tape"))
            update_rig(rig.rig_path, {"track.home": zero}, "survey home")
            await daemon.reload()
            results = dict(await commission(client, commissioning_plan(rigs, setup)))
    finally:
        camera.close()
        daemon.request_stop()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, 10.0)
    # every step of the demo's plan passes (it grows: the plan, not a count, says which)
    assert {"calibrate_intrinsics", "calibrate_head"} <= results.keys()
    assert all(r["passed"] for r in results.values()), {
        op: r["reasons"] for op, r in results.items()
    }
    lens = results["calibrate_intrinsics"]
    true_lens = rigs.true_camera()
    for key in INTRINSIC_KEYS:
        err = lens["camera"][key] - getattr(true_lens, key)
        assert abs(err) < 3.0 * lens["sigma"][key], (key, err, lens["sigma"][key])
    head = results["calibrate_head"]
    truth = rigs.true_kinematics()
    err = local_error(np.array(head["m_cr"]), truth.T_r_c)
    sigma = np.sqrt(np.diag(np.array(head["m_cr_covariance"])))
    assert np.all(np.abs(err) < 3.0 * sigma), ("M_cr", err, sigma)
    err = local_error(np.array(head["T_w_track"]), truth.track.T_w_track)
    sigma = np.sqrt(np.diag(np.array(head["T_w_track_covariance"])))
    assert np.all(np.abs(err) < 3.0 * sigma), ("T_w_track", err, sigma)
    spec = load_rig(rig.rig_path)  # what the daemon reads from now on
    np.testing.assert_allclose(spec.head.m_cr.matrix, head["m_cr"])
    np.testing.assert_allclose(spec.track.placement.matrix, head["T_w_track"])
    assert spec.head.m_cr.provenance.method.startswith("calibrate head")
    check = results["calibrate_check"]
    # the check's views are new ones; what they measure is what the error budget predicts
    assert check["predicted_sigma_px"] is not None
    assert check["rms_px"] < 3.0 * check["predicted_sigma_px"], check["reasons"]
