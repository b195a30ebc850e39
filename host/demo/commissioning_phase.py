"""The demo's commissioning: an installer's session on the simulated rig, through the daemon.

What the installer does, in order: place a ChArUco board on a stand under the track and survey
its pose (1 mm, 1 mrad), home the trolley and survey where the controller's zero is (1 mm), then
run `calibrate_intrinsics`, `calibrate_head` and `calibrate_check` against the running daemon's
control socket (cal11's operations, `host.commissioning.client`). Each passing step writes the
rig file the daemon reads; the experiments then load it. The board's true pose, the true zero
and the true lens stay in the simulator: the daemon's camera renders them, nothing else does.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil_sim.camera import PlacedBoard
from hil_sim.runner import Simulation
from host.calibration.board import BoardSpec
from host.commissioning.client import CommissioningPlan, RunFailedError, commission
from host.control.client import ControlClient
from host.demo.daemon_phase import RunningDaemon
from host.demo.rigs import DemoRigs
from host.demo.world import SimWorld
from host.geometry.transforms import FloatArray, euler_zyx, make_T, rot_x, rotvec_to_R
from host.rig import Provenance, Scalar, update_rig
from host.rig.schema import SURVEY_SIGMA_MM
from protocol.enums import Inputs

BOARD = BoardSpec(squares_x=8, squares_y=6, square_mm=70.0, marker_mm=52.0)
BOARD_ALONG_MM = 1200.0  # the stand: this far along the track from the power-on position
BOARD_ASIDE_MM = 400.0  # ... and this far to the left of it
BOARD_BELOW_MM = 2500.0  # ... this far below the track
BOARD_MIN_Z_MM = 500.0
BOARD_SURVEY_SIGMA_MM = 1.0
BOARD_SURVEY_SIGMA_RAD = 1e-3
STATION_SPACING_MM = 1000.0  # intrinsics and head views from the board's station and around it
CHECK_OFFSET_MM = 500.0  # the acceptance test looks from stations not used to calibrate
RING_DOWN_S = 0.5  # after homing, before the zero is surveyed (the rotor rings ~0.2 s)
READY_TIMEOUT_S = 60.0
POLL_S = 0.5  # status computes the error budget: do not load the daemon's loop with it
UM_PER_MM = 1000.0
HOMED = int(Inputs.HOMED)
ZERO_SURVEY_SALT = 0x2E80


@dataclass(frozen=True)
class BoardSetup:
    """The board on its stand: where it truly is and where the installer's survey says."""

    placed: PlacedBoard  # the truth, rendered by the simulator's camera
    T_w_b_surveyed: FloatArray  # what the host is told
    s_mm: float  # the track position above it


def place_board(rigs: DemoRigs, seed: int) -> BoardSetup:
    """A board face up under the track, turned a little; its survey is off by 1 mm, 1 mrad."""
    rng = np.random.default_rng([seed, 0xB0A2D])
    hi = rigs.travel_mm()[1]
    s = min(rigs.start_s_mm() + BOARD_ALONG_MM, hi - STATION_SPACING_MM)
    T = rigs.host_kinematics().track.pose(s)  # the installer places it by the drawing
    left_w = -T[:3, 1]  # the trolley's y points right of travel
    centre = T[:3, 3] + BOARD_ASIDE_MM * left_w
    centre[2] = max(BOARD_MIN_Z_MM, centre[2] - BOARD_BELOW_MM)
    yaw = float(np.arctan2(T[1, 0], T[0, 0])) + rng.uniform(-0.3, 0.3)
    R = rot_x(np.pi) @ euler_zyx(yaw, rng.normal(0, 0.05), rng.normal(0, 0.05))
    T_true = make_T(R, centre - R @ BOARD.centre_mm)
    w = rng.normal(0.0, BOARD_SURVEY_SIGMA_RAD, 3)
    t = rng.normal(0.0, BOARD_SURVEY_SIGMA_MM, 3)
    surveyed = T_true @ make_T(rotvec_to_R(w), t)
    return BoardSetup(PlacedBoard(BOARD.make(), T_true), surveyed, s)


def survey_zero(world: SimWorld, seed: int) -> float:
    """Where the controller's zero sits on the track, as a 1 mm survey finds it (trolley still).

    The surveyor reads the standing trolley's position and the controller's at the same moment:
    here the plant's true arc length and the firmware's, under the simulator's lock.
    """

    def simultaneous(sim: Simulation) -> float:
        return float(sim.truth().s_mm - sim.firmware.position_um / UM_PER_MM)

    true_zero = float(world.with_truth(simultaneous))
    rng = np.random.default_rng([seed, ZERO_SURVEY_SALT])
    return true_zero + float(rng.normal(0.0, SURVEY_SIGMA_MM))


def make_commissioner(
    setup: BoardSetup, seed: int, log: Callable[[str], None]
) -> Callable[[RunningDaemon, DemoRigs, SimWorld], Any]:
    """The demo's commissioning session (run_demo's `commission`)."""

    async def session(daemon: RunningDaemon, rigs: DemoRigs, world: SimWorld) -> dict[str, Any]:
        client = await ControlClient.connect_unix(str(daemon.socket_path))
        async with client:
            await _wait(client, lambda s: bool(s.get("link_up")), "link up")
            log("commissioning: homing")
            await client.request("home")
            await _wait(client, _ready_and_homed, "homed")
            await asyncio.sleep(RING_DOWN_S)
            home = survey_zero(world, seed)
            update_rig(
                daemon.rig_path,
                {"track.home": Scalar(home, SURVEY_SIGMA_MM, Provenance.now("survey (tape)"))},
                "survey home",
            )
            await daemon.reload()
            plan = commissioning_plan(rigs, setup)
            t0 = time.monotonic()
            error = ""
            try:
                steps = await commission(client, plan, _progress(log))
            except RunFailedError as exc:  # reported, and the experiments say "not commissioned"
                ctl = (await client.request("status")).get("controller", {})
                error = f"{exc} (controller {ctl.get('state')}, faults {ctl.get('fault_names')})"
                log(f"commissioning: {error}")
                steps = []
        return {
            "home_survey_mm": home,
            "board_s_mm": setup.s_mm,
            "duration_s": time.monotonic() - t0,
            "steps": [{"op": op, **_plain(result)} for op, result in steps],
            "passed": bool(steps) and all(r.get("passed") for _, r in steps) and not error,
            "error": error,
        }

    return session


def commissioning_plan(rigs: DemoRigs, setup: BoardSetup) -> CommissioningPlan:
    """Intrinsics around the board, head from three stations, the check from two others."""
    lo, hi = rigs.travel_mm()

    def within(values: list[float]) -> list[float]:
        return [min(max(v, lo + 200.0), hi - 200.0) for v in values]

    s = setup.s_mm
    stations = within([s - STATION_SPACING_MM, s, s + STATION_SPACING_MM])
    check = within([s - CHECK_OFFSET_MM, s + CHECK_OFFSET_MM])
    board = BOARD.to_dict()
    pose = setup.T_w_b_surveyed.tolist()
    centre = (setup.T_w_b_surveyed @ np.append(BOARD.centre_mm, 1.0))[:3].tolist()
    sigma = {"board_sigma_mm": BOARD_SURVEY_SIGMA_MM, "board_sigma_rad": BOARD_SURVEY_SIGMA_RAD}
    return (
        CommissioningPlan()
        .intrinsics(centre, stations, board=board)
        .add("calibrate_head", board_pose=pose, board=board, stations_mm=stations, **sigma)
        .add("calibrate_check", board_pose=pose, board=board, stations_mm=check)
    )


def _ready_and_homed(status: dict[str, Any]) -> bool:
    """The controller stands in READY with its zero referenced."""
    ctl = status.get("controller", {})
    inputs = ctl.get("inputs")
    homed = isinstance(inputs, int) and bool(inputs & HOMED)
    return ctl.get("state") == "READY" and homed


async def _wait(client: ControlClient, ok: Callable[[dict[str, Any]], bool], what: str) -> None:
    """Poll `status` until ok(status), or TimeoutError naming what did not happen."""
    deadline = time.monotonic() + READY_TIMEOUT_S
    status: dict[str, Any] = {}
    while time.monotonic() < deadline:
        status = await client.request("status")
        if ok(status):
            return
        await asyncio.sleep(POLL_S)
    raise TimeoutError(f"commissioning: not {what} within {READY_TIMEOUT_S} s ({status})")


def _progress(log: Callable[[str], None]) -> Callable[[dict[str, Any]], None]:
    """Print a run's phase when it changes."""
    last = {"phase": ""}

    def show(progress: dict[str, Any]) -> None:
        phase = str(progress.get("phase", ""))
        if phase and phase != last["phase"]:
            last["phase"] = phase
            log(f"commissioning: {phase}")

    return show


def _plain(result: dict[str, Any]) -> dict[str, Any]:
    """The JSON-able part of a step's result."""
    keep = ("passed", "reasons", "camera", "sigma", "rms_px", "views", "report", "written")
    return {k: result[k] for k in keep if k in result}
