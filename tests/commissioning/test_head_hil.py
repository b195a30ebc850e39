"""HIL: head, acceptance check and latency calibrations through the real daemon on the simulator.

The daemon's own code (host.demo.daemon_phase.running_daemon: the real controller factory and
frame loop) runs on the firmware mirror and plant behind a pty, with seeded installation
tolerances; its camera renders a surveyed board through the true rig and lens (test_hil's).
The installer's session is the demo's: home, survey the controller's zero (1 mm), then
`calibrate_intrinsics`, `calibrate_head` and `calibrate_check` over the control socket, then
`calibrate_latency` from passes by the board. The simulator's truth is used only in the
assertions below.
"""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path

import numpy as np
import pytest

from host.commissioning.client import commission
from host.control.client import ControlClient
from host.demo.commissioning_phase import BOARD, commissioning_plan, place_board, survey_zero
from host.demo.daemon_phase import running_daemon
from host.demo.rigs import DemoRigs
from host.demo.world import SimWorld
from host.geometry.transforms import R_to_rotvec
from host.rig import INTRINSIC_KEYS, Provenance, Scalar, load_rig, save_rig, update_rig
from host.rig.schema import SURVEY_SIGMA_MM
from tests.commissioning.test_hil import BoardCamera
from tests.commissioning.test_home_hil import until_at_rest

SEED = 3
# Views are captured at rest: a slow camera loses nothing there and leaves the link its CPU.
CAMERA_FPS = 4.0
# `status` computes the error budget on the daemon's loop: polled faster, on a loaded machine it
# delays the heartbeats past the controller's watchdog (as the demo's commissioning says).
POLL_S = 1.0
READY_TIMEOUT_S = 90.0


def local_error(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """δ with truth = est · exp(δ): (rotation vector, translation), as the covariances are."""
    d = np.linalg.inv(est) @ truth
    return np.concatenate([R_to_rotvec(d[:3, :3]), d[:3, 3]])


async def until_link_up(client: ControlClient) -> None:
    """Poll `status` (once a POLL_S: it computes the error budget) until the link is up."""
    deadline = time.monotonic() + READY_TIMEOUT_S
    while not (await client.request("status")).get("link_up"):
        assert time.monotonic() < deadline, "the controller link did not come up"
        await asyncio.sleep(POLL_S)


@pytest.mark.slow
async def test_head_check_and_latency_on_the_simulator_through_the_real_daemon(
    tmp_path: Path,
) -> None:
    rigs = DemoRigs.make(None, SEED, tolerances=True)
    rig_file = tmp_path / "rig.toml"
    save_rig(rigs.nominal, rig_file)
    world = SimWorld(rigs.scenario(SEED), "pty")
    setup = place_board(rigs, SEED)
    # the board alone (no scene): a fifth of the scene's CPU, so the loop keeps its heartbeats
    camera = BoardCamera(
        world, rigs.true_kinematics(), rigs.true_camera(), setup.placed, SEED, fps=CAMERA_FPS
    )
    await world.start()
    try:
        async with running_daemon(world, rig_file, tmp_path / "daemon", camera) as daemon:
            client = await ControlClient.connect_unix(str(daemon.socket_path))
            async with client:
                await until_link_up(client)
                await client.request("home")
                await asyncio.sleep(0.5)  # HOMING by now
                await until_at_rest(str(daemon.socket_path), homed=True)
                await asyncio.sleep(0.5)  # the rotor rings down before the zero is surveyed
                zero = Scalar(survey_zero(world, SEED), SURVEY_SIGMA_MM, Provenance.now("tape"))
                update_rig(rig_file, {"track.home": zero}, "survey home")
                await daemon.reload()
                plan = commissioning_plan(rigs, setup).add(
                    "calibrate_latency", station_mm=setup.s_mm, passes=4,
                    board_pose=setup.T_w_b_surveyed.tolist(), board=BOARD.to_dict(),
                )  # fmt: skip
                results = dict(await commission(client, plan))
    finally:
        camera.close()
        await world.stop()
    assert [r["passed"] for r in results.values()] == [True, True, True, True], {
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
    spec = load_rig(rig_file)  # what the daemon reads from now on
    np.testing.assert_allclose(spec.head.m_cr.matrix, head["m_cr"])
    np.testing.assert_allclose(spec.track.placement.matrix, head["T_w_track"])
    assert spec.head.m_cr.provenance.method.startswith("calibrate head")
    check = results["calibrate_check"]
    # the views the check takes are new; what they measure is what the budget predicts
    assert check["predicted_sigma_px"] is not None
    assert check["rms_px"] < 3.0 * check["predicted_sigma_px"], check["reasons"]
    latency = results["calibrate_latency"]
    # the camera delivers DELIVERY_S + |N(0, jitter)| after the exposure: that mean is the truth
    clock = camera.clock
    true_ms = (clock.delivery_s + clock.jitter_s * math.sqrt(2.0 / math.pi)) * 1e3
    err_ms = latency["latency_ms"] - true_ms
    assert abs(err_ms) < 3.0 * latency["sigma_ms"], (err_ms, latency["sigma_ms"])
    assert load_rig(rig_file).camera.latency.value == pytest.approx(latency["latency_ms"])
