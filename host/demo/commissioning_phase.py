"""The demo's commissioning: an installer's session on the simulated rig, through the daemon.

What the installer does, in order: place a ChArUco board on a stand under the track and survey
its pose (1 mm, 1 mrad), stick photogrammetry targets on the workpiece's feature points, home
the trolley, then run the commissioning plan against the running daemon's control socket
(`host.commissioning.client`): survey home, calibrate intrinsics, head and latency, survey the
workpiece with the camera, and the acceptance check. Each passing step writes the rig file the
daemon reads; the experiments then load it. The board's true pose, the true zero, the true
workpiece and the true lens stay in the simulator: the daemon's camera renders them and its
rangefinder reads the true walls, nothing else does.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil_sim.camera import PlacedBoard
from host.calibration.board import BoardSpec
from host.commissioning.client import CommissioningPlan, RunFailedError, run_op
from host.control.client import ControlClient
from host.demo.daemon_phase import RunningDaemon
from host.demo.experiments import DEMO_WATCHDOG_MS, LOOK_AHEAD_PAN_RAD, LOOK_AHEAD_TILT_RAD
from host.demo.rigs import DemoRigs
from host.demo.world import SimWorld
from host.geometry.transforms import FloatArray, euler_zyx, make_T, rot_x, rotvec_to_R
from host.rig import RigSpec
from host.station.parts import load_parts, sidecar_path
from protocol.enums import Inputs

BOARD = BoardSpec(squares_x=8, squares_y=6, square_mm=70.0, marker_mm=52.0)
BOARD_ALONG_MM = 1200.0  # the stand: this far along the track from the power-on position
BOARD_ASIDE_MM = 400.0  # ... and this far to the left of it
BOARD_BELOW_MM = 2500.0  # ... this far below the track, at most
BOARD_FILL = 0.64  # ... or nearer, so that its width fills this much of the image (a wide lens)
BOARD_MIN_Z_MM = 500.0
BOARD_SURVEY_SIGMA_MM = 1.0
BOARD_SURVEY_SIGMA_RAD = 1e-3
STATION_SPACING_MM = 1000.0  # intrinsics and head views from the board's station and around it
CHECK_OFFSET_MM = 500.0  # the acceptance test looks from stations not used to calibrate
# the workpiece survey's stations, from the power-on position (the static observation points
# are at 0 and 300 mm, the full demo's last at 2000 mm): rays across the workpiece
WORKPIECE_STATIONS_MM = (-250.0, 300.0, 1100.0)
MIN_TARGETS = 3
HOME_CLEARANCE_MM = 100.0
# latency: passes past the board long enough for several frames at constant speed (the
# commissioning camera runs at 5 fps), the board in view all along
LATENCY_SPAN_MM = 600.0
LATENCY_SPEED_MM_S = 300.0
LATENCY_PASSES = 4
FIRST_HOME_MAX_SIGMA_MM = 10.0  # the first zero, before the head is calibrated
READY_TIMEOUT_S = 60.0
POLL_S = 0.5  # status computes the error budget: do not load the daemon's loop with it
HOMED = int(Inputs.HOMED)
STEP_TRIES = 2
CLOCK_SYNCED_US = 1000.0


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
    cam = rigs.host.camera
    width_mm = BOARD.squares_x * BOARD.square_mm
    fill_mm = cam.intrinsics.get("fx") * width_mm / (BOARD_FILL * cam.width)
    centre[2] = max(BOARD_MIN_Z_MM, centre[2] - min(BOARD_BELOW_MM, fill_mm))
    yaw = float(np.arctan2(T[1, 0], T[0, 0])) + rng.uniform(-0.3, 0.3)
    R = rot_x(np.pi) @ euler_zyx(yaw, rng.normal(0, 0.05), rng.normal(0, 0.05))
    T_true = make_T(R, centre - R @ BOARD.centre_mm)
    w = rng.normal(0.0, BOARD_SURVEY_SIGMA_RAD, 3)
    t = rng.normal(0.0, BOARD_SURVEY_SIGMA_MM, 3)
    surveyed = T_true @ make_T(rotvec_to_R(w), t)
    return BoardSetup(PlacedBoard(BOARD.make(), T_true), surveyed, s)


def feature_points(spec: RigSpec) -> FloatArray:
    """The model's feature points (its sidecar's P1..Pn, model frame), where targets are stuck."""
    parts = load_parts(sidecar_path(spec.workpiece.model))
    return np.array([p.position_mm for p in parts.points], dtype=np.float64).reshape(-1, 3)


def make_commissioner(
    setup: BoardSetup, seed: int, log: Callable[[str], None],
    stick_targets: Callable[[bool], None] = lambda on: None,
) -> Callable[[RunningDaemon, DemoRigs, SimWorld], Any]:  # fmt: skip
    """The demo's commissioning session (run_demo's `commission`).

    `stick_targets(True)` puts the photogrammetry targets on the workpiece for its survey and
    `stick_targets(False)` takes them off again, so that they never sit in a board's view.
    """

    async def session(daemon: RunningDaemon, rigs: DemoRigs, world: SimWorld) -> dict[str, Any]:
        client = await ControlClient.connect_unix(str(daemon.socket_path))
        async with client:
            await _wait(client, lambda s: bool(s.get("link_up")), "link up")
            # One process runs simulator, daemon and rendering on a shared machine: give the
            # controller's watchdog the slack the experiments have too (PROTOCOL.md §9).
            await client.request("param_set", param="WATCHDOG_MS", value=DEMO_WATCHDOG_MS)
            await _clear_watchdog(client)  # a daemon slow to start let the controller fault
            log("commissioning: homing")
            await client.request("home")
            await _wait(client, _ready_and_homed, "homed")
            await _wait_clock(client)  # samples are stamped through it (a survey averages them)
            plan = commissioning_plan(rigs, setup)
            t0 = time.monotonic()
            error = ""
            try:
                steps = await _run_plan(client, plan, _progress(log), stick_targets)
            except RunFailedError as exc:  # reported, and the experiments say "not commissioned"
                ctl = (await client.request("status")).get("controller", {})
                error = f"{exc} (controller {ctl.get('state')}, faults {ctl.get('fault_names')})"
                log(f"commissioning: {error}")
                steps = []
        return {
            "board_s_mm": setup.s_mm,
            "duration_s": time.monotonic() - t0,
            "steps": [{"op": op, **_plain(result)} for op, result in steps],
            "passed": bool(steps) and all(r.get("passed") for _, r in steps) and not error,
            "error": error,
        }

    return session


def commissioning_plan(rigs: DemoRigs, setup: BoardSetup) -> CommissioningPlan:
    """The installer's steps, in order, each through the daemon's control socket.

    The home first, by the rangefinder on the end wall ahead (σ from the drawing's rig: the
    beam's origin is only known that well until the head is calibrated); intrinsics around the
    board; the head from three stations (the home's σ goes into the track's); the workpiece by
    the camera, targets on its feature points triangulated through the calibrated rig from
    stations around where it is watched; the latency from passes past the board; last the
    acceptance test from two stations not used to calibrate.
    """
    lo, hi = rigs.travel_mm()

    def within(values: list[float]) -> list[float]:
        return [min(max(v, lo + 200.0), hi - 200.0) for v in values]

    s = setup.s_mm
    stations = within([s - STATION_SPACING_MM, s, s + STATION_SPACING_MM])
    check = within([s - CHECK_OFFSET_MM, s + CHECK_OFFSET_MM])
    start = rigs.start_s_mm()
    behind_home = rigs.home_switch_mm() + HOME_CLEARANCE_MM  # the controller stops short of it
    survey_at = within([max(start + d, behind_home) for d in WORKPIECE_STATIONS_MM])
    board = BOARD.to_dict()
    pose = setup.T_w_b_surveyed.tolist()
    centre = (setup.T_w_b_surveyed @ np.append(BOARD.centre_mm, 1.0))[:3].tolist()
    sigma = {"board_sigma_mm": BOARD_SURVEY_SIGMA_MM, "board_sigma_rad": BOARD_SURVEY_SIGMA_RAD}
    nominal = rigs.host
    plan = (
        CommissioningPlan()
        .add("survey_home", **first_home_survey(nominal))
        .intrinsics(centre, stations, board=board)
        .add(
            "calibrate_head", board_pose=pose, board=board, stations_mm=stations, reuse_views=True,
            **sigma,
        )  # the intrinsics run's views: the same board, stations and zero
    )  # fmt: skip
    points = feature_points(nominal)
    if len(points) >= MIN_TARGETS:
        plan.add(
            "survey_workpiece", method="camera", model_points_mm=points.tolist(),
            stations_mm=survey_at,
        )  # fmt: skip
    plan.add(
        "calibrate_latency", board_pose=pose, board=board, station_mm=s, span_mm=LATENCY_SPAN_MM,
        speed_mm_s=LATENCY_SPEED_MM_S, passes=LATENCY_PASSES,
    )  # fmt: skip
    return plan.add("calibrate_check", board_pose=pose, board=board, stations_mm=check)


def first_home_survey(nominal: RigSpec) -> dict[str, Any]:
    """`survey_home`'s arguments before the head is calibrated: the beam along the track onto
    the end wall ahead, its origin only known as well as the drawing's placement and mount."""
    beam_origin = float(
        np.hypot(max(nominal.track.placement.sigma_mm), max(nominal.rangefinder.mount.sigma_mm))
    )
    return {
        "pan_rad": LOOK_AHEAD_PAN_RAD, "tilt_rad": LOOK_AHEAD_TILT_RAD,
        "noise_mm": nominal.rangefinder.noise_mm, "rig_sigma_mm": beam_origin,
        "max_sigma_mm": FIRST_HOME_MAX_SIGMA_MM,
    }  # fmt: skip


async def _run_plan(
    client: ControlClient, plan: CommissioningPlan, progress: Callable[[dict[str, Any]], None],
    stick_targets: Callable[[bool], None],
) -> list[tuple[str, dict[str, Any]]]:  # fmt: skip
    """The plan's steps in order, stopping after the first that fails (as `commission`)."""
    results: list[tuple[str, dict[str, Any]]] = []
    for op, args in plan.steps:
        targets = op == "survey_workpiece" and args.get("method") == "camera"
        stick_targets(targets)
        t0 = time.monotonic()
        try:
            result = await _run_step(client, op, args, progress)
        finally:
            stick_targets(False)
        results.append((op, {**result, "duration_s": round(time.monotonic() - t0, 1)}))
        if not result.get("passed", False):
            break
    return results


async def _run_step(
    client: ControlClient, op: str, args: dict[str, Any],
    progress: Callable[[dict[str, Any]], None],
) -> dict[str, Any]:  # fmt: skip
    """One step; a run that ended in an error (a command timed out on a starved link) is run
    once more, as an installer would, after clearing a watchdog fault it left."""
    for attempt in range(STEP_TRIES):
        try:
            return await run_op(client, op, args, progress)
        except RunFailedError as exc:
            if attempt + 1 == STEP_TRIES or exc.status.get("state") != "error":
                raise
            link = await client.request("link_stats")
            keep = ("drops", "unsynced_samples", "rtt_ms", "clock_sigma_us", "sink_errors")
            seen = {k: link.get(k) for k in keep}
            progress({"phase": f"{op} again after: {exc} (link {seen})"})
            await _clear_watchdog(client)
            if not _ready_and_homed(await client.request("status")):
                await client.request("home")  # the same switch and index: the same zero
            await _wait(client, _ready_and_homed, "ready and homed")
    raise AssertionError("unreachable")


async def _clear_watchdog(client: ControlClient) -> None:
    """Clear a latched WATCHDOG fault (only that: any other fault stops the session)."""
    await asyncio.sleep(POLL_S)  # a STATUS since the link came up
    ctl = (await client.request("status")).get("controller", {})
    if ctl.get("state") == "FAULT" and ctl.get("fault_names") == ["WATCHDOG"]:
        await client.request("clear")
        await asyncio.sleep(POLL_S)


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


async def _wait_clock(client: ControlClient) -> None:
    """Until the link's clock sync has converged (its σ below CLOCK_SYNCED_US), or a timeout."""
    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        sigma = (await client.request("link_stats")).get("clock_sigma_us")
        if isinstance(sigma, int | float) and sigma < CLOCK_SYNCED_US:
            return
        await asyncio.sleep(POLL_S)


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
    keep = (
        "passed", "reasons", "camera", "sigma", "rms_px", "views", "report", "written",
        "duration_s", "home_mm", "sigma_mm", "latency_ms", "sigma_ms", "rms_mm", "sigma_px",
    )  # fmt: skip
    return {k: result[k] for k in keep if k in result}
