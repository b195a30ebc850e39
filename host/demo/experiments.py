"""The paper's experiments (§5.2, §5.3) and the drift experiment, run through the daemon's code.

Everything here drives the rig through `host.link.Controller` and reads camera frames through
the frame loop, as on a real rig; the simulator's ground truth arrives only inside each frame's
`truth` and is used only by the scoring.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from hil_sim.runner import Simulation
from host.commissioning import home_run
from host.commissioning.frames import FrameTap, RangeTap
from host.commissioning.motion import RigIO
from host.demo.feeds import TrackFeed
from host.demo.scoring import (
    PROBE_DEPTH_MM,
    Score,
    aimed_errors,
    centre_error,
    chain_errors,
    summary,
    true_zero_mm,
    workpiece_errors,
)
from host.demo.world import SceneTruth, SimWorld
from host.frames.registrar import Registrar, Registration
from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import Wireframe
from host.geometry.rangefinder import RangeScene
from host.geometry.transforms import make_T
from host.link import Controller, ControllerRejected, LinkError
from host.link.clocksync import ClockSync
from host.registration.pose_buffer import PoseSource
from host.service.wiring import stream_rates
from protocol import ParamId
from protocol.enums import Fault, State

FloatArray = NDArray[np.float64]
T = TypeVar("T")
Progress = Callable[[str, float], None]

# The daemon's telemetry rates (an ENCODER_SAMPLE is 26 bytes on the wire, so 115200 baud
# cannot carry 500 Hz), with the rangefinder on: the hall's walls are surveyed.
LINK_KINDS = {"pty": "serial", "xbee": "xbee", "can": "can"}  # the demo's links → the daemon's
STREAM_RATES_HZ = {link: stream_rates(kind, ranging=True) for link, kind in LINK_KINDS.items()}
# Drift loop: the head turns the rangefinder (and camera) to look ahead along the track,
# level, so the beam meets the hall's end walls nearly head-on on the straights.
LOOK_AHEAD_PAN_RAD = 0.0
LOOK_AHEAD_TILT_RAD = math.pi / 2
SETTLED_PITCH_FRACTION = 0.125  # ~2 px: far above the fused error, far below a pitch's 15 px
HOMING_RUN_UP_MM = 100.0  # drive to just before the home switch fast, then seek it slowly
SETTLE_S = 0.2  # ring-down after the head reports it arrived
HEAD_TIMEOUT_S = 10.0
DEMO_WATCHDOG_MS = 5_000
HEAD_TOLERANCE_RAD = 2e-3
ACCEL_MM_S2 = 800.0  # what the loop also uses; the stepper keeps up with margin
MAX_FRAMES = 4  # frames per wanted observation before the point gives up
BLANK_PX = 2  # a frame the camera did not render (SimCameraSource.render_every)
FIT_MARGIN_MM = 150.0  # keep the runs this far from an open track's limit switch
STILL_MM = 0.07  # about one encoder count (0.0635 mm): a standing trolley moves less than this
STILL_WINDOW_S = 0.25  # ... for this long (the rotor's ring-down after a stop is ~0.2 s)
STILL_POLL_S = 0.01
STILL_TIMEOUT_S = 3.0
UM_PER_MM = 1000.0
STATUS_WAIT_S = 0.3  # STATUS streams at 2-20 Hz and is sent on every state change
FAULT_CLEAR_TRIES = 3
HOME_SURVEY_SAMPLES = 100  # the readings of a standing trolley, averaged (σ 0.1 mm)


@dataclass(frozen=True)
class Plan:
    """What to run; `quick()` is the short variant for the test suite."""

    observation_mm: tuple[float, ...] = (0.0, 300.0, 2000.0)
    observations: int = 30
    travel_speed_mm_s: float = 500.0  # between observations: the controller's MAX_SPEED
    moving_length_mm: float = 1500.0
    moving_speed_mm_s: float = 100.0
    moving_samples: int = 30
    loop_length_mm: float = 16_000.0
    loop_speed_mm_s: float = 450.0
    skips_at_fraction: tuple[float, ...] = (0.35, 0.7)
    elongation: float = 0.005

    @staticmethod
    def quick() -> Plan:
        """About a quarter of the full run."""
        return Plan(
            observation_mm=(0.0, 300.0),
            observations=8,
            moving_length_mm=300.0,
            moving_speed_mm_s=300.0,
            moving_samples=8,
            loop_length_mm=4_600.0,  # the first straight and part of a corner
            loop_speed_mm_s=500.0,
            skips_at_fraction=(0.5,),
        )

    def fitted(self, start_s_mm: float, home_s_mm: float, travel_mm: tuple[float, float]) -> Plan:
        """This plan within a track's travel (a short open track cannot take the full runs)."""
        room = travel_mm[1] - FIT_MARGIN_MM - start_s_mm
        observations = tuple(o for o in self.observation_mm if o <= room) or (0.0,)
        loop_room = travel_mm[1] - FIT_MARGIN_MM - home_s_mm - HOMING_RUN_UP_MM
        return dataclasses.replace(
            self,
            observation_mm=observations,
            moving_length_mm=max(0.0, min(self.moving_length_mm, room)),
            loop_length_mm=max(0.0, min(self.loop_length_mm, loop_room)),
        )


@dataclass
class Collector:
    """Routes frame-loop results to whoever is listening now."""

    sink: Callable[[tuple[Registration, Registration]], None] | None = None
    latest: tuple[Registration, Registration] | None = None

    def __call__(self, result: tuple[Registration, Registration]) -> None:
        self.latest = result
        if self.sink is not None:
            self.sink(result)

    async def gather(self, count: int, timeout_s: float) -> list[tuple[Registration, Registration]]:
        """The next `count` results."""
        got: list[tuple[Registration, Registration]] = []
        done = asyncio.get_running_loop().create_future()

        def take(r: tuple[Registration, Registration]) -> None:
            got.append(r)
            if len(got) >= count and not done.done():
                done.set_result(None)

        self.sink = take
        try:
            await asyncio.wait_for(done, timeout_s)
        finally:
            self.sink = None
        return got


@dataclass(frozen=True)
class Truth:
    """The simulator's rig and lens, for scoring only (the host never computes with these)."""

    rig: Rig
    camera: CameraModel


@dataclass
class Bench:
    """The host side of the demo: controller, feeds, registrars, frame results.

    `rig`, `camera`, `workpiece` and `latency_ns` are the host's calibrated belief; `truth` is
    the simulator's, used by the scoring only.
    """

    ctrl: Controller
    rig: Rig
    camera: CameraModel
    model: Wireframe
    feed: TrackFeed
    workpiece: Callable[[int], FloatArray]
    truth: Truth
    home_switch_s_mm: float  # where the drawing puts the home switch (the host's rig file)
    latency_ns: int = 0
    home_survey_sigma_mm: float = 0.0  # the walls' survey σ (the home survey's σ)
    ranges: RangeTap | None = None  # the controller's rangefinder readings (home survey)
    scene: RangeScene | None = None  # the host's surveyed walls
    range_noise_mm: float = 1.0
    # the error budget's predicted overlay σ (px) of the model's centre at (s, pan, tilt)
    predicted_px: Callable[[float, float, float], float] | None = None
    home_truth_mm: float | None = None  # true arc length of the zero (scoring only)
    collector: Collector = field(default_factory=Collector)
    snapshots: list[tuple[str, Any]] = field(default_factory=list)
    faults_cleared: list[str] = field(default_factory=list)  # watchdog faults recovered from
    # (the zero in use, the home survey's reading of it then): the re-homed zero's reference
    home_reference_mm: tuple[float, float] | None = None
    # each home survey's σ from its readings' noise alone (what two surveys from one geometry
    # do not share: the walls' and the rig's part of their σ is common and cancels)
    survey_noise_mm: list[float] = field(default_factory=list)

    async def command(self, send: Callable[[], Awaitable[T]]) -> T:
        """Send a motion command; if the controller refuses it because a stalled demo process
        let its watchdog fault it, clear that fault (re-homing if the zero was lost) and send
        it once more. Any other refusal stops the run, as it would stop an operator."""
        try:
            return await send()
        except ControllerRejected as exc:
            snap = self.ctrl.snapshot()
            if exc.state is not State.FAULT or snap.faults != Fault.WATCHDOG:
                raise
        await self.ctrl.clear_fault()
        self.faults_cleared.append("WATCHDOG")
        await asyncio.sleep(STATUS_WAIT_S)
        if not self.ctrl.snapshot().homed:  # the same switch and index: the same zero
            motion = await self.ctrl.home(speed_mm_s=200.0)
            await motion.done(timeout_s=60.0)
            self.feed.set_home(self.feed.home_s_mm)
        return await send()

    def registrars(self) -> tuple[Registrar, Registrar]:
        """Encoder-only (draws the overlay) and fused (scored only)."""
        lat = self.latency_ns
        raw = PoseSource(self.rig, self.feed.raw, self.feed.head, exposure_latency_ns=lat)
        fused = PoseSource(self.rig, self.feed.fused, self.feed.head, exposure_latency_ns=lat)
        return (
            Registrar(raw, self.camera, self.model, self.workpiece, draw=True),
            Registrar(fused, self.camera, self.model, self.workpiece, draw=False),
        )

    def process(self) -> Callable[[Frame], tuple[Registration, Registration]]:
        """The frame loop's per-frame work."""
        raw, fused = self.registrars()
        return lambda frame: (raw(frame), fused(frame))

    async def move(self, s_track_mm: float, speed_mm_s: float) -> None:
        """Drive the trolley to a track position (controller coordinates = track − home)."""
        motion = await self.command(
            lambda: self.ctrl.move_to(s_track_mm - self.feed.home_s_mm, speed_mm_s, ACCEL_MM_S2)
        )
        distance = abs(s_track_mm - (self.feed.last_enc_mm or s_track_mm))
        await motion.done(timeout_s=10.0 + 2.0 * distance / speed_mm_s)

    async def drive_and_aim(
        self, s_track_mm: float, speed_mm_s: float, target_w: FloatArray
    ) -> None:
        """Drive to a track position with the head turning toward a world point on the way."""
        angles = self.rig.aim(s_track_mm, target_w)
        await self.command(lambda: self.ctrl.set_head(*angles))
        await self.move(s_track_mm, speed_mm_s)
        await self.aim(s_track_mm, target_w)

    async def aim(self, s_track_mm: float, target_w: FloatArray) -> None:
        """Point the head at a world point from a track position, and let it settle."""
        await self.point_head(*self.rig.aim(s_track_mm, target_w))

    async def point_head(self, pan: float, tilt: float) -> None:
        """Turn the head to these angles and let it settle."""
        await self.command(lambda: self.ctrl.set_head(pan, tilt))
        loop = asyncio.get_running_loop()
        deadline = loop.time() + HEAD_TIMEOUT_S
        while loop.time() < deadline:
            await asyncio.sleep(0.05)
            _, angles = self.feed.head.window()
            if len(angles) and np.max(np.abs(angles[-1] - (pan, tilt))) < HEAD_TOLERANCE_RAD:
                break
        await asyncio.sleep(SETTLE_S)


async def start_host(bench: Bench, link: str) -> list[str]:
    """Streams on at what the link carries, then home; the latched faults it had to clear.

    Only a WATCHDOG fault is cleared (a host that went quiet before, e.g. the commissioning
    daemon on a starved machine); any other fault or an e-stop stops the run, as it would stop
    an operator.
    """
    await bench.ctrl.set_streams(STREAM_RATES_HZ[link])
    # The demo runs simulator, registration and host in one process on a shared machine, so
    # its loop can stall past the default 500 ms; the watchdog faults a standing controller
    # too (PROTOCOL.md §9), so give it the slack a real host on its own machine does not need.
    await bench.ctrl.set_param(ParamId.WATCHDOG_MS, DEMO_WATCHDOG_MS)
    cleared: list[str] = []
    for _ in range(FAULT_CLEAR_TRIES):
        await asyncio.sleep(STATUS_WAIT_S)  # a STATUS has arrived: the snapshot is current
        snap = bench.ctrl.snapshot()
        if snap.state is not State.FAULT:
            break
        if snap.faults != Fault.WATCHDOG:
            break  # any other fault stops the run at homing, as it would stop an operator
        await bench.ctrl.clear_fault()
        cleared.append("WATCHDOG")
    motion = await bench.ctrl.home(speed_mm_s=200.0)
    await motion.done(timeout_s=60.0)
    return cleared


async def wait_still(bench: Bench) -> None:
    """Wait until the encoder has stood still for STILL_WINDOW_S (or STILL_TIMEOUT_S passed).

    A motion is done when its profile ends, but the stepper's rotor then rings about the field
    (~14 Hz, ζ ≈ 0.2: ±1 mm of chain, gone after ~0.2 s): a survey taken during the ring-down
    reads a trolley that is still moving.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + STILL_TIMEOUT_S
    seen: list[tuple[float, float]] = []
    while loop.time() < deadline:
        position = bench.ctrl.snapshot().position_mm
        if position is not None:
            seen.append((loop.time(), position))
            recent = [p for t, p in seen if t >= seen[-1][0] - STILL_WINDOW_S]
            if seen[-1][0] - seen[0][0] >= STILL_WINDOW_S and max(recent) - min(recent) < STILL_MM:
                return
        await asyncio.sleep(STILL_POLL_S)


async def survey_home(bench: Bench) -> float:
    """Track position of the controller's zero: the daemon's `survey home` measurement.

    The trolley stands still (the rotor's ring-down would be read into the survey), the head
    turns the rangefinder along the track at the end wall ahead, and the readings are solved for
    the arc length through the host's rig and surveyed walls (host.commissioning.home_run).
    """
    if bench.ranges is None or bench.scene is None:
        raise LinkError("no rangefinder or no surveyed walls: the zero cannot be surveyed")
    await wait_still(bench)
    # the drawing's home as the start: the arc lengths the solve starts from stay on the track
    io = RigIO(bench.ctrl, FrameTap(_NoCamera()), home_s_mm=bench.home_switch_s_mm)
    result = await home_run.survey_home(
        io, bench.ranges, bench.rig, bench.scene, LOOK_AHEAD_PAN_RAD, LOOK_AHEAD_TILT_RAD,
        HOME_SURVEY_SAMPLES, bench.range_noise_mm, bench.home_survey_sigma_mm, {},
    )  # fmt: skip
    if not result["passed"]:
        raise LinkError(f"the home survey failed: {'; '.join(result['reasons'])}")
    noise = bench.range_noise_mm / math.sqrt(HOME_SURVEY_SAMPLES) / abs(float(result["slope"]))
    bench.survey_noise_mm.append(noise)
    return float(result["home_mm"])


class _NoCamera:
    """The survey needs no frames."""

    def read(self) -> None:
        return None

    def close(self) -> None:
        return None


async def static_experiment(
    bench: Bench, plan: Plan, start_s: float, progress: Progress
) -> dict[str, Any]:
    """§5.2: repeated observations at points along the track; centre offset in mm and px."""
    centroid = bench.model.vertices.mean(axis=0)
    target = (bench.workpiece(0) @ np.append(centroid, 1.0))[:3]
    rows: dict[str, Any] = {}
    for i, offset in enumerate(plan.observation_mm):
        progress(f"static: observation point {offset:.0f} mm", i / len(plan.observation_mm))
        s = start_s + offset
        await bench.drive_and_aim(s, plan.travel_speed_mm_s, target)
        results: list[tuple[Registration, Registration]] = []
        scores: list[Score] = []
        # A frame with no pose (registered late on a loaded machine) is counted, not scored.
        while len(scores) < plan.observations and len(results) < MAX_FRAMES * plan.observations:
            got = (await bench.collector.gather(1, 30.0))[0]
            results.append(got)
            if (sc := centre_error(got[0], bench.truth.camera, centroid)) is not None:
                scores.append(sc)
        rows[f"{offset:.0f}"] = {
            "offset_mm": summary([sc.error_mm for sc in scores]),
            "offset_px": summary([sc.error_px for sc in scores]),
            "frames": len(results),
        }
        if bench.predicted_px is not None:
            pan, tilt = bench.rig.aim(s, target)
            rows[f"{offset:.0f}"]["predicted_sigma_px"] = bench.predicted_px(s, pan, tilt)
        drawn = [r for r, _ in results if r.image is not None and r.image.shape[0] > BLANK_PX]
        if drawn:
            bench.snapshots.append((f"Observation point {offset:.0f} mm", drawn[-1].image))
    return rows


async def moving_experiment(
    bench: Bench, plan: Plan, start_s: float, robot: MovingRobot, progress: Progress
) -> dict[str, Any]:
    """§5.3: the workpiece moves along X, the camera follows at the same speed; R of eq. 15."""
    centroid = bench.model.vertices.mean(axis=0)
    start_target = (robot.pose_at_ns(0) @ np.append(centroid, 1.0))[:3]
    await bench.drive_and_aim(start_s, plan.travel_speed_mm_s, start_target)
    progress("moving: tracking the robot", 0.0)
    loop = asyncio.get_running_loop()
    robot.start(loop.time())
    motion = await bench.command(
        lambda: bench.ctrl.move_to(
            start_s + plan.moving_length_mm - bench.feed.home_s_mm,
            plan.moving_speed_mm_s,
            ACCEL_MM_S2,
        )
    )
    collected: list[Score] = []

    def take(r: tuple[Registration, Registration]) -> None:
        sc = centre_error(r[0], bench.truth.camera, centroid)
        if sc is not None:
            collected.append(sc)

    bench.collector.sink = take
    try:
        await motion.done(timeout_s=10.0 + 2.0 * plan.moving_length_mm / plan.moving_speed_mm_s)
    finally:
        bench.collector.sink = None
    picks = np.linspace(0, len(collected) - 1, min(plan.moving_samples, len(collected)))
    samples = [collected[round(k)] for k in picks] if collected else []
    errors = [sc.error_mm for sc in samples]
    rms = summary(errors)["rms"]
    return {
        "samples": len(samples),
        "frames": len(collected),
        "error_mm": summary(errors),
        "error_px": summary([sc.error_px for sc in samples]),
        "R_percent": 100.0 * rms / plan.moving_length_mm,
        "length_mm": plan.moving_length_mm,
    }


async def drift_experiment(
    bench: Bench, world: SimWorld, plan: Plan, progress: Progress
) -> dict[str, Any]:
    """Beyond the paper: a loop with a stretched chain and tooth skips, encoder-only vs fused.

    Scored as the operator sees it: the overlay of the workpiece's centre, were the camera
    turned to it (`workpiece_errors`). The fused pose against the world frame (a probe 3 m on
    the optical axis, `aimed_errors`) is reported beside it: it adds the world placement's error
    (the board's survey), which the workpiece surveyed through the same rig shares and the
    overlay therefore never shows.
    """
    world.with_truth(lambda sim: sim.set_elongation(plan.elongation))
    await bench.command(lambda: bench.ctrl.set_head(LOOK_AHEAD_PAN_RAD, LOOK_AHEAD_TILT_RAD))
    await bench.move(bench.home_switch_s_mm + HOMING_RUN_UP_MM, plan.travel_speed_mm_s)
    motion = await bench.ctrl.home(speed_mm_s=200.0)
    await motion.done(timeout_s=60.0)
    # The same switch and sprocket index, but a stretched chain puts the zero elsewhere along
    # the track (the stretch of the chain up to it): the same survey as at the start, with the
    # same aim and rig, measures by how much; what both surveys share (rig, walls) cancels.
    await wait_still(bench)
    base, reference = bench.home_reference_mm or (bench.feed.home_s_mm, bench.feed.home_s_mm)
    surveyed = base + await survey_home(bench) - reference
    # The zero is where the two surveys put it apart, to their readings' noise: the filter's
    # prior on the offset (the homing's repeatability otherwise).
    bench.feed.set_home(surveyed, math.hypot(*bench.survey_noise_mm[-2:]))
    if (ranger := bench.feed.corrected.ranger) is not None:
        # The zero (at `base` in the rig's arc lengths) reads as `reference` through the range
        # model: the model's bias there (mount, walls), which fixes from the same geometry share.
        ranger.anchor_at(base, LOOK_AHEAD_PAN_RAD, LOOK_AHEAD_TILT_RAD, reference)
    await wait_still(bench)
    bench.home_truth_mm = true_zero_mm(world)  # scoring only: the stretch moved it a little
    await bench.point_head(LOOK_AHEAD_PAN_RAD, LOOK_AHEAD_TILT_RAD)
    start_enc = bench.feed.last_enc_mm or bench.feed.home_s_mm
    marks_before = bench.feed.marks_seen
    ranger = bench.feed.corrected.ranger
    range_before = dict(vars(ranger.stats)) if ranger else {}
    raw_scores: list[Score] = []
    fused_scores: list[Score] = []
    world_scores: list[Score] = []  # the fused pose against the world frame (probe on the axis)
    chain_scores: list[Score] = []  # the track error alone, in the host's own rig (scoring)
    along_mm: list[float] = []  # fused arc length less the true one in the host's zero (signed)
    home_offset = bench.feed.home_s_mm - (bench.home_truth_mm or bench.feed.home_s_mm)

    centroid = bench.model.vertices.mean(axis=0)
    target = (bench.workpiece(time.monotonic_ns()) @ np.append(centroid, 1.0))[:3]

    def take(r: tuple[Registration, Registration]) -> None:
        raw, fused = r
        truth = raw.truth
        if isinstance(truth, SceneTruth) and raw.T_w_c is not None and fused.T_w_c is not None:
            host, true = (bench.rig, bench.camera), (bench.truth.rig, bench.truth.camera)
            seen = (truth.T_w_p @ np.append(centroid, 1.0))[:3]
            raw_score, fused_score = workpiece_errors(r, truth, host, true, (target, seen))
            raw_scores.append(raw_score)
            fused_scores.append(fused_score)
            world_scores.append(aimed_errors((fused,), truth, host, true, target)[0])
            chain_scores.append(
                chain_errors((fused,), truth, (bench.rig, bench.camera), home_offset, target)[0]
            )
            along_mm.append(fused.s_mm - truth.s_mm - home_offset)

    skips = sorted(start_enc + f * plan.loop_length_mm for f in plan.skips_at_fraction)
    bench.collector.sink = take
    try:
        motion = await bench.command(
            lambda: bench.ctrl.move_to(
                start_enc + plan.loop_length_mm - bench.feed.home_s_mm, plan.loop_speed_mm_s, 800.0
            )
        )
        finished = asyncio.ensure_future(
            motion.done(timeout_s=10.0 + 2.0 * plan.loop_length_mm / plan.loop_speed_mm_s)
        )
        injected = 0
        skip_s: list[float] = []  # true positions of the injected skips (scoring only)
        clock_errors_us: list[float] = []
        while not finished.done():
            await asyncio.wait({finished}, timeout=0.05)
            clock_errors_us.append(clock_sync_error_us(bench, world))
            progress(
                "drift: loop with a stretched chain",
                (bench.feed.last_enc_mm or 0.0) / (start_enc + plan.loop_length_mm),
            )
            if injected < len(skips) and (bench.feed.last_enc_mm or 0.0) >= skips[injected]:
                skip_s.append(world.with_truth(_skip_tooth))
                injected += 1
        await finished
    finally:
        bench.collector.sink = None
    pitch_px = world.sim.scenario.chain.pitch_mm * bench.camera.fx / PROBE_DEPTH_MM
    return {
        "elongation": plan.elongation,
        "tooth_skips": len(plan.skips_at_fraction),
        "marks_seen": bench.feed.marks_seen - marks_before,
        "references_used": bench.feed.chain.stats.updates,
        "range_fixes": ranger.stats.fixes if ranger else 0,
        # what the loop's readings became (fixes, and refusals by reason)
        "range_loop": {k: v - range_before[k] for k, v in vars(ranger.stats).items()}
        if ranger
        else {},
        "skips_detected": bench.feed.chain.stats.skips_detected,
        "scale_estimate": float(bench.feed.chain.x[1]),
        "clock_sync_error_us": summary([abs(e) for e in clock_errors_us]),
        "encoder_only_px": summary([sc.error_px for sc in raw_scores]),
        "fused_px": summary([sc.error_px for sc in fused_scores]),
        "fused_world_px": summary([sc.error_px for sc in world_scores]),
        "fused_track_px": summary([sc.error_px for sc in chain_scores]),
        **skip_summary(fused_scores, skip_s, SETTLED_PITCH_FRACTION * pitch_px),
        "trace": {
            "s_mm": [sc.s_true_mm for sc in raw_scores],
            "encoder_only_px": [sc.error_px for sc in raw_scores],
            "fused_px": [sc.error_px for sc in fused_scores],
            "fused_along_mm": along_mm,
        },
    }


def _skip_tooth(sim: Simulation) -> float:
    """Inject one tooth skip; return where it happened (true arc length)."""
    sim.inject_tooth_skip(1)
    return sim.truth().s_mm


def skip_summary(scores: list[Score], skips_mm: list[float], settled_px: float) -> dict[str, Any]:
    """Per skip, the frames and travel until the fusion had put it right; the error elsewhere.

    A skip's window runs from the first frame past it to the first frame after that back under
    settled_px (an eighth of a pitch): the frames a user saw the overlay jump, fully or in part
    (a frame between the last uncorrected encoder sample and the first corrected one carries a
    share of the pitch). It begins earlier by the frames just before the skip that are off by
    as much: a frame exposed between the last reading that agreed and the first that showed the
    skip is given the pitch times the chance the skip came before it, also when it did not.
    """
    windows: list[tuple[int, int]] = []
    for skip in skips_mm:
        start = next((i for i, sc in enumerate(scores) if sc.s_true_mm >= skip), len(scores))
        earliest = windows[-1][1] if windows else 0  # never into the previous skip's window
        while start > earliest and scores[start - 1].error_px >= settled_px:
            start -= 1
        end = next(
            (i for i in range(start, len(scores)) if scores[i].error_px < settled_px),
            len(scores),
        )
        windows.append((start, end))
    travel = [  # None: never put right before the run ended
        scores[end].s_true_mm - scores[start].s_true_mm if end < len(scores) else None
        for start, end in windows
    ]
    outside = [
        sc.error_px for i, sc in enumerate(scores) if not any(a <= i < b for a, b in windows)
    ]
    return {
        "skip_frames": [end - start for start, end in windows],
        "skip_travel_mm": travel,
        "fused_px_outside_skip_windows": summary(outside),
    }


def clock_sync_error_us(bench: Bench, world: SimWorld) -> float:
    """The demo's own link: its clock-sync error now (`clock_error_us`)."""
    return clock_error_us(bench.ctrl.session.clock, world)


def clock_error_us(clock: ClockSync, world: SimWorld) -> float:
    """Scoring only: a clock sync's mapping of the latest MCU tick minus when that tick truly
    happened, in µs."""

    def latest(sim: Simulation) -> tuple[int, float]:
        return sim.board.mcu_us & 0xFFFF_FFFF, sim.time_s - sim.dt_s

    mcu_us, true_s = world.with_truth(latest)
    return (clock.peek_host_ns(mcu_us) - world.host_time_ns(true_s)) / 1000.0


@dataclass
class MovingRobot:
    """The §5.3 workpiece: a robot driving along a direction at uniform speed, from a start pose.

    It drives along an axis of its own base (the workpiece frame): `direction_w` is that axis as
    the host's start pose puts it in the world. The true robot drives along the same axis of
    its true frame, so a workpiece surveyed off by a rotation moves off by it too, as it would.
    """

    start_pose: FloatArray
    direction_w: FloatArray
    speed_mm_s: float
    length_mm: float
    _t0: float | None = None  # when it set off, host monotonic seconds
    direction_p: FloatArray = field(init=False)

    def __post_init__(self) -> None:
        self.direction_p = self.start_pose[:3, :3].T @ np.asarray(self.direction_w, np.float64)

    def start(self, t0: float) -> None:
        """Set off at t0 (the event loop's clock, which is time.monotonic)."""
        self._t0 = t0

    def pose_at_ns(self, t_ns: int, start_pose: FloatArray | None = None) -> FloatArray:
        """T_w_p at a host monotonic time, from `start_pose` (default: the robot's own)."""
        start = self.start_pose if start_pose is None else start_pose
        if self._t0 is None:
            return start
        travel = min(max(0.0, t_ns / 1e9 - self._t0) * self.speed_mm_s, self.length_mm)
        out: FloatArray = start @ make_T(np.eye(3), travel * self.direction_p)
        return out
