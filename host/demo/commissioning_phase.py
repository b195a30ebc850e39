"""The demo's commissioning: an installer's session on the simulated rig, through the daemon.

What the installer does, in order: place a ChArUco board on a stand under the track and survey
its pose (1 mm, 1 mrad), stick photogrammetry targets on the workpiece's feature points, home
the trolley, then run the commissioning plan against the running daemon's control socket
(`host.commissioning.client`): survey home, calibrate intrinsics, head and latency, the
acceptance check, and survey the workpiece with the camera. Each passing step writes the rig
file the daemon reads; the experiments then load it. The board's true pose, the true zero, the
true workpiece and the true lens stay in the simulator: the daemon's camera renders them and
its rangefinder reads the true walls, nothing else does.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil_sim.camera import PlacedBoard
from host.calibration.board import BoardSpec
from host.commissioning.client import CommissioningPlan, RunFailedError, run_op
from host.commissioning.plan import IMAGE_TARGETS, board_plan
from host.control.client import ControlClient
from host.demo.daemon_phase import RunningDaemon
from host.demo.experiments import (
    DEMO_WATCHDOG_MS,
    LOOK_AHEAD_PAN_RAD,
    LOOK_AHEAD_TILT_RAD,
    clock_error_us,
)
from host.demo.rigs import DemoRigs, model_of
from host.demo.world import SimWorld
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import (
    FloatArray,
    euler_zyx,
    make_T,
    rot_x,
    rotvec_to_R,
    transform_points,
)
from host.link import Controller
from host.rig import RigSpec
from host.station.parts import load_parts, sidecar_path
from protocol.enums import Inputs

BOARD = BoardSpec(squares_x=8, squares_y=6, square_mm=70.0, marker_mm=52.0)  # as printed
BOARD_ALONG_MM = 1200.0  # the stand: this far along the track from the power-on position
BOARD_ASIDE_MM = 400.0  # ... and this far to the left of it (or the right: `place_board`)
# ... and as far below the track as makes the board's longer side fill this much of the image's
# shorter side seen from above it (the board turns in the image with the pan, and the views that
# put it near a corner must still see most of it)
BOARD_FILL = 0.8
BOARD_MIN_BELOW_MM = 1500.0  # nearer, the stations 1 m to either side would see it too steeply
BOARD_MIN_Z_MM = 500.0  # the lowest stand
BOARD_MAX_CROSSED = 0.2  # ... and in no view the workpiece's edges cross more of its markers
BOARD_HALL_CLEARANCE_MM = 300.0  # the stand stays this far inside the hall's walls
# where else the stand may go along a straight, after the first place: every this many mm
BOARD_ALONG_STEP_MM = 300.0
BOARD_SURVEY_SIGMA_MM = 1.0
BOARD_SURVEY_SIGMA_RAD = 1e-3
# The intrinsics and head views from the board's station and this far to either side of it, all
# on one straight (the head calibration solves the track's placement, not its arcs' radii); on
# a straight too short for that, closer, down to the minimum (shorter, the views of the board
# differ too little in tilt)
STATION_SPACING_MM = 1000.0
MIN_STATION_SPACING_MM = 500.0
STRAIGHT_END_MARGIN_MM = 50.0  # the stations this far inside the straight (the zero's survey)
TRAVEL_MARGIN_MM = 200.0  # and inside the travel between the limit switches
CHECK_OFFSET = 0.5  # the acceptance test looks from stations not used to calibrate (× spacing)
# ... with the board at the image's centre and at two opposite corners: the lens's distortion
# and the chain's errors show there as at the other two (three views a station, six in all)
CHECK_TARGETS = ((0.5, 0.5), (0.3, 0.3), (0.7, 0.7))
# the workpiece survey's stations, from the power-on position (the static observation points
# are at 0 and 300 mm, the full demo's last at 2000 mm): rays across the workpiece
WORKPIECE_STATIONS_MM = (-250.0, 300.0, 1100.0)
MIN_TARGETS = 3
HOME_CLEARANCE_MM = 100.0
# latency: passes past the board long enough for several frames at constant speed (the
# commissioning camera runs at 10 fps: 1.4 s at 300 mm/s between the ramps, about 14 frames a
# pass, 28 over two, as four passes gave at 5 fps), the board in view all along
LATENCY_SPAN_MM = 600.0
LATENCY_SPEED_MM_S = 300.0
LATENCY_PASSES = 2
FIRST_HOME_MAX_SIGMA_MM = 10.0  # the first zero, before the head is calibrated
READY_TIMEOUT_S = 60.0
POLL_S = 0.5  # status computes the error budget: do not load the daemon's loop with it
HOMED = int(Inputs.HOMED)
STEP_TRIES = 2
CLOCK_SYNCED_US = 1000.0
CLOCK_WATCH_S = 0.25  # how often the scoring samples the daemon's clock error


@dataclass(frozen=True)
class BoardSetup:
    """The board on its stand: where it truly is and where the installer's survey says."""

    placed: PlacedBoard  # the truth, rendered by the simulator's camera
    T_w_b_surveyed: FloatArray  # what the host is told
    s_mm: float  # the track position above it
    board: BoardSpec = BOARD  # as printed for this rig's lens and track height
    spacing_mm: float = STATION_SPACING_MM  # the head stations' distance from s_mm


def place_board(rigs: DemoRigs, seed: int) -> BoardSetup:
    """A board face up under the track, turned a little; its survey is off by 1 mm, 1 mrad.

    The installer works from the drawing (the nominal rig) and the live view: the board is as
    far below the track as its lens wants (`board_for_lens`), beside the track above one
    straight, far enough from its ends that the stations to either side stay on it
    (`board_stretches`). Of the places along those straights (nearest first to
    `BOARD_ALONG_MM` past the power-on position, every `BOARD_ALONG_STEP_MM`) and to either
    side of the track (the left first) inside the hall, the board goes to the first where
    every planned view of it is within the head's limits and has the workpiece's edges across
    none of it (`board_view_conflicts`); the least bad if none is.
    """
    rng = np.random.default_rng([seed, 0xB0A2D])
    turn = (rng.uniform(-0.3, 0.3), rng.normal(0, 0.05), rng.normal(0, 0.05))
    w = rng.normal(0.0, BOARD_SURVEY_SIGMA_RAD, 3)
    t = rng.normal(0.0, BOARD_SURVEY_SIGMA_MM, 3)
    rig, camera = rigs.host_kinematics(), rigs.host_camera()
    board, below = board_for_lens(rigs)
    places: list[tuple[tuple[int, int], float, int, float, float, FloatArray]] = []
    for s, spacing in board_places(rigs):
        for side in (1.0, -1.0):
            T_w_b = stand_pose(rig, board, s, side, below, turn)
            if not inside_hall(rigs.host, (T_w_b @ np.append(board.centre_mm, 1.0))[:3]):
                continue
            badness = board_view_conflicts(rigs, rig, camera, board, T_w_b, s, spacing)
            places.append((badness, -spacing, len(places), s, spacing, T_w_b))
            if badness == (0, 0):  # the first good place
                break
        if places and places[-1][0] == (0, 0):
            break
    if not places:
        raise ValueError(f"rig {rigs.host.name!r}: no place for the board inside the hall")
    *_, s, spacing, T_true = min(places, key=lambda p: p[:3])  # the first of the least bad
    surveyed = T_true @ make_T(rotvec_to_R(w), t)
    return BoardSetup(PlacedBoard(board.make(), T_true), surveyed, s, board, spacing)


def stand_pose(
    rig: Rig, board: BoardSpec, s_mm: float, side: float, below_mm: float,
    turn: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> FloatArray:  # fmt: skip
    """The board face up `below_mm` under the track (the lowest stand at least) and
    `BOARD_ASIDE_MM` to its left (side 1) or right (side -1) at s_mm, turned by `turn` (yaw
    from the track's heading, then pitch and roll), as the installer places it by the drawing."""
    T = rig.track.pose(s_mm)
    left_w = -T[:3, 1]  # the trolley's y points right of travel
    centre = T[:3, 3] + side * BOARD_ASIDE_MM * left_w
    centre[2] = max(BOARD_MIN_Z_MM, centre[2] - below_mm)
    yaw = float(np.arctan2(T[1, 0], T[0, 0])) + turn[0]
    R = rot_x(np.pi) @ euler_zyx(yaw, turn[1], turn[2])
    return make_T(R, centre - R @ board.centre_mm)


def board_stretches(rigs: DemoRigs) -> list[tuple[float, float, float]]:
    """Where the board's station may be: (first, last, spacing) per straight of the drawing's
    track long enough for stations `spacing` to either side of it (`STATION_SPACING_MM`, or
    closer on a short straight, down to `MIN_STATION_SPACING_MM`), each within
    `STRAIGHT_END_MARGIN_MM` of the straight's ends and `TRAVEL_MARGIN_MM` of the travel's
    (arc lengths as the trolley travels: a closed loop's straights where the travel meets
    them). On a track without such a straight, anywhere along the travel, 1 m apart."""
    track = rigs.host_kinematics().track
    lo, hi = rigs.travel_mm()
    lo, hi = lo + TRAVEL_MARGIN_MM, hi - TRAVEL_MARGIN_MM
    laps = range(math.floor(lo / track.length_mm), math.floor(hi / track.length_mm) + 1)
    out = []
    start = 0.0
    for segment in track.segments:
        if segment.curvature_per_mm == 0.0:
            for lap in laps if track.closed else (0,):
                a = start + lap * track.length_mm + STRAIGHT_END_MARGIN_MM
                b = a + segment.length_mm - 2.0 * STRAIGHT_END_MARGIN_MM
                a, b = max(a, lo), min(b, hi)
                spacing = min(STATION_SPACING_MM, (b - a) / 2.0)
                if spacing >= MIN_STATION_SPACING_MM:
                    out.append((a + spacing, b - spacing, spacing))
        start += segment.length_mm
    if not out and hi - lo >= 2.0 * STATION_SPACING_MM:
        out.append((lo + STATION_SPACING_MM, hi - STATION_SPACING_MM, STATION_SPACING_MM))
    return out


def board_places(rigs: DemoRigs) -> list[tuple[float, float]]:
    """The stations the installer tries for the board, (s, spacing), nearest first to
    `BOARD_ALONG_MM` past the power-on position: there (or as near as a straight allows), then
    every `BOARD_ALONG_STEP_MM` along each straight."""
    first = rigs.start_s_mm() + BOARD_ALONG_MM
    places: list[tuple[float, float]] = []
    for a, b, spacing in board_stretches(rigs):
        near = min(max(first, a), b)
        steps = np.arange(-math.floor((near - a) / BOARD_ALONG_STEP_MM),
                          math.floor((b - near) / BOARD_ALONG_STEP_MM) + 1)  # fmt: skip
        places += [(float(near + k * BOARD_ALONG_STEP_MM), spacing) for k in steps]
    return sorted(places, key=lambda p: (abs(p[0] - first), p[0]))


def board_for_lens(rigs: DemoRigs) -> tuple[BoardSpec, float]:
    """The board as printed for this lens, and how far below the track it stands.

    The default board at the distance where its longer side fills `BOARD_FILL` of the image's
    shorter side; where the floor (a long lens on a low track) or the stations' slant (a wide
    lens) does not allow that distance, a print scaled to fill the same at the one allowed.
    """
    cam = rigs.host.camera
    focal = min(cam.intrinsics.get("fx"), cam.intrinsics.get("fy"))
    longer = max(BOARD.squares_x, BOARD.squares_y) * BOARD.square_mm
    wanted = focal * longer / (BOARD_FILL * min(cam.width, cam.height))
    height = float(rigs.host_kinematics().track.pose(rigs.start_s_mm())[2, 3])
    below = min(max(wanted, BOARD_MIN_BELOW_MM), height - BOARD_MIN_Z_MM)
    if abs(below - wanted) < 1.0:
        return BOARD, wanted
    k = below / wanted
    square, marker = round(BOARD.square_mm * k, 1), round(BOARD.marker_mm * k, 1)
    return BoardSpec(BOARD.squares_x, BOARD.squares_y, square, marker, BOARD.dictionary), below


def inside_hall(spec: RigSpec, point_w: FloatArray) -> bool:
    """On the inner side of every surveyed wall (their normals point into the hall)."""
    for surface in spec.hall.surfaces:
        if surface.radius_mm > 0.0:
            continue  # a bounded target, not a wall
        n = np.asarray(surface.normal, dtype=np.float64)
        depth = float((point_w - np.asarray(surface.point_mm)) @ (n / np.linalg.norm(n)))
        if abs(n[2]) < 0.5 and depth < BOARD_HALL_CLEARANCE_MM:
            return False
    return True


def board_view_conflicts(
    rigs: DemoRigs, rig: Rig, camera: CameraModel, board: BoardSpec, T_w_b: FloatArray,
    s_mm: float, spacing_mm: float = STATION_SPACING_MM,
) -> tuple[int, int]:  # fmt: skip
    """Over the board views of the commissioning plan for a board at T_w_b above s_mm (the
    intrinsics and head views, the acceptance check's, and the latency passes' ends): (views in
    which the drawing's workpiece edges cross more than `BOARD_MAX_CROSSED` of the markers in
    view, views that cannot be planned). The simulated camera, like a real one behind a thin
    wire frame, draws the edges over the board, and a marker an edge crosses does not decode."""
    intrinsics, check = board_stations(rigs, s_mm, spacing_mm)
    centre = (T_w_b @ np.append(board.centre_mm, 1.0))[:3]
    head = rigs.host.head
    limits = ((head.pan_min_rad, head.pan_max_rad), (head.tilt_min_rad, head.tilt_max_rad))
    views = board_plan(rig, camera, centre, intrinsics, IMAGE_TARGETS, limits)
    views += board_plan(rig, camera, centre, check, CHECK_TARGETS, limits)
    at = board_plan(rig, camera, centre, within_travel(rigs, [s_mm]), [(0.5, 0.5)], limits)
    planned = len(intrinsics) * len(IMAGE_TARGETS) + len(check) * len(CHECK_TARGETS) + 1
    missing = planned - len(views) - len(at)
    poses = [rig.T_c_w(v.s_mm, v.pan_rad, v.tilt_rad) for v in views]
    for v in at:  # the head stays aimed from the middle while the trolley passes
        passes = within_travel(rigs, [v.s_mm - LATENCY_SPAN_MM / 2, v.s_mm + LATENCY_SPAN_MM / 2])
        poses += [rig.T_c_w(s, v.pan_rad, v.tilt_rad) for s in [v.s_mm, *passes]]
    markers_b = np.asarray(board.make().getObjPoints(), dtype=np.float64).reshape(-1, 3)
    markers_w = transform_points(T_w_b, markers_b)
    model = model_of(rigs.host)
    model_w = transform_points(rigs.host_workpiece(), model.vertices)
    size = np.array([camera.width, camera.height], dtype=np.float64)
    spoilt = 0
    for T_c_w in poses:
        quads, q_ok = _pinhole(camera, T_c_w, markers_w)
        quads, q_ok = quads.reshape(-1, 4, 2), q_ok.reshape(-1, 4)
        seen = q_ok.all(axis=1) & ((quads >= 0) & (quads <= size)).all(axis=(1, 2))
        ends, e_ok = _pinhole(camera, T_c_w, model_w)
        lines = ends[model.edges][e_ok[model.edges].all(axis=1)]
        crossed = _segments_cross(lines, quads[seen])
        spoilt += int(seen.sum()) > 0 and crossed.sum() > BOARD_MAX_CROSSED * seen.sum()
    return int(spoilt), int(missing)


def _pinhole(
    camera: CameraModel, T_c_w: FloatArray, points_w: FloatArray
) -> tuple[FloatArray, Any]:
    """Pixels through K only (distortion folds far points back into the image), and whether
    each point is in front of the camera."""
    pc = transform_points(T_c_w, points_w)
    front = pc[:, 2] > 1.0
    uv = (pc @ camera.K.T)[:, :2] / np.where(front, pc[:, 2], 1.0)[:, None]
    return uv, front


def _segments_cross(lines: FloatArray, quads: FloatArray) -> Any:
    """Per convex quad (K, 4, 2): whether any segment (N, 2, 2) passes through it (Cyrus-Beck)."""
    if len(lines) == 0 or len(quads) == 0:
        return np.zeros(len(quads), dtype=bool)
    edge = np.roll(quads, -1, axis=1) - quads  # (K, 4, 2)
    area = np.sum(quads[:, :, 0] * np.roll(quads[:, :, 1], -1, axis=1), axis=1) - np.sum(
        quads[:, :, 1] * np.roll(quads[:, :, 0], -1, axis=1), axis=1
    )
    inward = np.stack([-edge[..., 1], edge[..., 0]], axis=-1) * np.sign(area)[:, None, None]
    a, d = lines[:, 0], lines[:, 1] - lines[:, 0]  # (N, 2)
    # n·(a + t d - p) >= 0 on every side: num + t den >= 0
    num = np.einsum("kjc,nc->nkj", inward, a) - np.einsum("kjc,kjc->kj", inward, quads)[None]
    den = np.einsum("kjc,nc->nkj", inward, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -num / den
    enter = np.where(den > 0, t, -np.inf).max(axis=2).clip(0.0, None)
    leave = np.where(den < 0, t, np.inf).min(axis=2).clip(None, 1.0)
    parallel_out = ((den == 0) & (num < 0)).any(axis=2)
    return ((enter <= leave) & ~parallel_out).any(axis=0)


def board_stations(
    rigs: DemoRigs, s_mm: float, spacing_mm: float = STATION_SPACING_MM
) -> tuple[list[float], list[float]]:
    """The intrinsics and head stations around the board's, and the acceptance test's."""
    intrinsics = within_travel(rigs, [s_mm - spacing_mm, s_mm, s_mm + spacing_mm])
    off = CHECK_OFFSET * spacing_mm
    return intrinsics, within_travel(rigs, [s_mm - off, s_mm + off])


def within_travel(rigs: DemoRigs, values: list[float]) -> list[float]:
    """Arc lengths kept `TRAVEL_MARGIN_MM` inside the travel."""
    lo, hi = rigs.travel_mm()
    return [min(max(v, lo + TRAVEL_MARGIN_MM), hi - TRAVEL_MARGIN_MM) for v in values]


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
            clock = ClockWatch(lambda: _daemon_clock_error_us(daemon, world))
            watch = asyncio.create_task(clock.run())
            try:
                steps = await _run_plan(client, plan, _progress(log), stick_targets, clock)
            except RunFailedError as exc:  # reported, and the experiments say "not commissioned"
                ctl = (await client.request("status")).get("controller", {})
                error = f"{exc} (controller {ctl.get('state')}, faults {ctl.get('fault_names')})"
                log(f"commissioning: {error}")
                steps = []
            finally:
                watch.cancel()
        return {
            "board_s_mm": setup.s_mm,
            "duration_s": time.monotonic() - t0,
            "steps": [{"op": op, **_plain(result)} for op, result in steps],
            "passed": bool(steps) and all(r.get("passed") for _, r in steps) and not error,
            "error": error,
        }

    return session


@dataclass
class ClockWatch:
    """Scoring only: the daemon's clock-sync error, sampled through the commissioning, so each
    step's result says what the link's clock did while it ran. Measured against the runner's
    schedule (`SimWorld.host_time_ns`), as the drift experiment's figure is: a simulator
    running behind it shows as error too."""

    error_us: Callable[[], float | None]
    samples: list[float] = field(default_factory=list)

    async def run(self) -> None:
        """Sample until cancelled."""
        while True:
            error = self.error_us()
            if error is not None:
                self.samples.append(error)
            await asyncio.sleep(CLOCK_WATCH_S)

    def since(self, start: int) -> dict[str, float]:
        """|error| over the samples from index `start` on: median and max, µs."""
        errors = np.abs(self.samples[start:])
        if not len(errors):
            return {}
        return {"median": round(float(np.median(errors)), 1), "max": round(float(errors.max()), 1)}


def _daemon_clock_error_us(daemon: RunningDaemon, world: SimWorld) -> float | None:
    """The daemon's clock-sync error now against the simulator's clock (None before a fit)."""
    ctrl = daemon.daemon.controller
    if not isinstance(ctrl, Controller) or not ctrl.session.clock.ready:
        return None
    return clock_error_us(ctrl.session.clock, world)


def commissioning_plan(rigs: DemoRigs, setup: BoardSetup) -> CommissioningPlan:
    """The installer's steps, in order, each through the daemon's control socket.

    The home first, by the rangefinder on the end wall ahead (σ from the drawing's rig: the
    beam's origin is only known that well until the head is calibrated); intrinsics around the
    board; the head from three stations (the home's σ goes into the track's); the track survey
    through the first corner (its place relative to the zero and the arcs' radius, which no
    view on the first straight sees: the zero and the placement move together; with the zero
    right the daemon's pose feed no longer takes the marks for tooth skips, which biased the
    latency of seed 2: docs/COMMISSIONING.md); the latency from passes past the board; the
    acceptance test of the board's chain from two stations not used to calibrate; last the
    workpiece by the camera, targets on its feature points triangulated through the calibrated
    rig from stations around where it is watched. The check and the latency need nothing of
    the workpiece (nor the check of the latency: its views are taken at rest), and the
    workpiece's stations lie between the board's and home: the trolley ends the session near
    home, where the experiments home it again.
    """
    s = setup.s_mm
    stations, check = board_stations(rigs, s, setup.spacing_mm)
    start = rigs.start_s_mm()
    behind_home = rigs.home_switch_mm() + HOME_CLEARANCE_MM  # the controller stops short of it
    survey_at = within_travel(rigs, [max(start + d, behind_home) for d in WORKPIECE_STATIONS_MM])
    board = setup.board.to_dict()
    pose = setup.T_w_b_surveyed.tolist()
    centre = (setup.T_w_b_surveyed @ np.append(setup.board.centre_mm, 1.0))[:3].tolist()
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
    plan.add("survey_track")  # the first corner and the arcs' radius: nothing above sees them
    plan.add(
        "calibrate_latency", board_pose=pose, board=board, station_mm=s, span_mm=LATENCY_SPAN_MM,
        speed_mm_s=LATENCY_SPEED_MM_S, passes=LATENCY_PASSES,
    )  # fmt: skip
    plan.add(
        "calibrate_check", board_pose=pose, board=board, stations_mm=check,
        image_targets=[list(t) for t in CHECK_TARGETS],
    )  # fmt: skip
    points = feature_points(nominal)
    if len(points) >= MIN_TARGETS:
        plan.add(
            "survey_workpiece", method="camera", model_points_mm=points.tolist(),
            stations_mm=survey_at,
        )  # fmt: skip
    return plan


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
    stick_targets: Callable[[bool], None], clock: ClockWatch,
) -> list[tuple[str, dict[str, Any]]]:  # fmt: skip
    """The plan's steps in order, stopping after the first that fails (as `commission`)."""
    results: list[tuple[str, dict[str, Any]]] = []
    for op, args in plan.steps:
        targets = op == "survey_workpiece" and args.get("method") == "camera"
        stick_targets(targets)
        t0, first = time.monotonic(), len(clock.samples)
        try:
            result = await _run_step(client, op, args, progress)
        finally:
            stick_targets(False)
        scores = {"clock_error_us": clock.since(first), **await _chain_counters(client)}
        results.append((op, {**result, "duration_s": round(time.monotonic() - t0, 1), **scores}))
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


async def _chain_counters(client: ControlClient) -> dict[str, Any]:
    """The daemon's chain filter after a step, cumulative: the demo injects no tooth skip
    during commissioning, so a skip it took there was most likely false (it moved the pose
    the calibrations read by a pitch)."""
    link = await client.request("link_stats")
    keys = ("skips_detected", "references_rejected", "references_used", "chain_offset_mm")
    return {"chain": {k: link[k] for k in keys if k in link}}


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
        "corner_mm", "corner_sigma_mm", "radius_change_mm", "radius_sigma_mm", "chain",
        "clock_error_us",
    )  # fmt: skip
    return {k: result[k] for k in keep if k in result}
