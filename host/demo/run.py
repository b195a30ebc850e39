"""`orbitar demo`: the paper's experiments end to end on the simulator, and a report.

The emulator (firmware mirror + plant) runs in real time behind a real link; the daemon's own
controller, pose buffers, frame loop and registration run against it exactly as on a rig.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil_sim.camera import FrameClock
from hil_sim.true_rig import Tolerances, parameter_errors
from host.commissioning.frames import RangeTap
from host.demo.commissioning_phase import feature_points, make_commissioner, place_board
from host.demo.daemon_phase import running_daemon
from host.demo.experiments import (
    LINK_KINDS,
    LOOK_AHEAD_PAN_RAD,
    LOOK_AHEAD_TILT_RAD,
    Bench,
    MovingRobot,
    Plan,
    Truth,
    drift_experiment,
    moving_experiment,
    start_host,
    static_experiment,
    survey_home,
    wait_still,
)
from host.demo.feeds import TrackFeed
from host.demo.propagation_report import propagation_results
from host.demo.report_pages import write_report
from host.demo.rigs import DemoRigs, model_of
from host.demo.scoring import true_zero_mm
from host.demo.world import SimCameraSource, SimWorld
from host.experiments.budget import inputs_from_rig, overlay_sigma
from host.frames.loop import FrameLoop
from host.frames.stamps import SteadyClockSource
from host.fusion import rig_references
from host.fusion.rig_references import chain_config
from host.link import Controller, LinkError
from host.link.controller import MotionFailed
from host.rig import RigError, RigSpec, build_scene, load_rig, save_rig
from host.rig.schema import NOMINAL, SURVEY_SIGMA_MM
from host.service.wiring import frame_wait_s

BAR_WIDTH = 30
RENDER_EVERY = 8  # experiment frames rendered as images (the report's snapshots); all registered
# The daemon's camera while commissioning. Views are captured at rest, a frame after rest: the
# wait is a frame period; the latency passes use every frame. A moving frame renders in ~40 ms
# here, one at rest (the same scene, new noise) in ~9 ms: at 10 fps ~0.4 and ~0.1 core.
COMMISSIONING_FPS = 10.0


@dataclass
class Progress:
    """A one-line progress bar on stderr."""

    phase_weights: dict[str, float]
    done_weight: float = 0.0
    _phase: str = ""
    _t0: float = field(default_factory=time.monotonic)
    _shown: tuple[int, str] = (-1, "")
    _last_label: str = ""

    def __call__(self, label: str, fraction: float) -> None:
        phase = label.split(":")[0]
        if phase != self._phase:
            self.done_weight += self.phase_weights.get(self._phase, 0.0)
            self._phase = phase
        total = sum(self.phase_weights.values())
        now = self.done_weight + self.phase_weights.get(phase, 0.0) * min(max(fraction, 0.0), 1.0)
        percent = round(100 * now / total)
        if (percent, label) == self._shown:
            return
        self._shown = (percent, label)
        elapsed = time.monotonic() - self._t0
        if not sys.stderr.isatty():
            if label != self._last_label:  # a log, not a redrawn bar
                sys.stderr.write(f"{elapsed:6.1f}s {percent:3d}% {label}\n")
                self._last_label = label
            return
        filled = BAR_WIDTH * percent // 100
        bar = "#" * filled + "-" * (BAR_WIDTH - filled)
        sys.stderr.write(f"\r[{bar}] {percent:3d}% {elapsed:5.1f}s {label:<45.45}")
        sys.stderr.flush()

    def finish(self) -> None:
        """End the bar's line."""
        if sys.stderr.isatty():
            sys.stderr.write("\n")


@dataclass
class LoopLag:
    """How late the event loop wakes up: a stalled loop starves the link's heartbeats."""

    period_s: float = 0.05
    max_ms: float = 0.0

    async def run(self) -> None:
        """Sleep a period at a time and keep the worst overshoot."""
        loop = asyncio.get_running_loop()
        while True:
            t = loop.time()
            await asyncio.sleep(self.period_s)
            self.max_ms = max(self.max_ms, (loop.time() - t - self.period_s) * 1e3)


async def run_demo(
    link: str,
    quick: bool,
    out_dir: Path,
    seed: int = 1,
    rig_path: Path | None = None,
    tolerances: bool = False,
    commission: bool = False,
    plan: Plan | None = None,
) -> dict[str, Any]:
    """Run everything; return the results (also written to out_dir).

    The host starts from the rig description (`rig_path`, default the paper's rig in a surveyed
    hall); the simulator runs the true rig: the description itself, or with `tolerances` the
    description off by seeded installation tolerances. With `commission`, the daemon runs on the
    simulated rig first and the commissioning (host.demo.commissioning_phase) writes OUT/rig.toml
    through its control socket; the experiments then use that file's (calibrated) rig only.
    """
    rigs = DemoRigs.make(rig_path, seed, tolerances)
    out_dir.mkdir(parents=True, exist_ok=True)
    host_rig_file = out_dir / "rig.toml"  # what the host knows; commissioning writes here
    save_rig(rigs.host, host_rig_file, "the demo's host rig (nominal)")
    sc = rigs.scenario(seed)
    world = SimWorld(sc, link)
    results: dict[str, Any] = {"link": link, "quick": quick, "seed": seed, "rig": rigs.host.name}
    results["mode"] = {"tolerances": tolerances, "commissioned": False}
    await world.start()
    try:
        if commission:
            results["commissioning"] = await _commission(rigs, world, host_rig_file, seed)
            rigs = dataclasses.replace(rigs, host=load_rig(host_rig_file))
            results["mode"]["commissioned"] = bool(results["commissioning"]["passed"])
            results["mode"]["calibrated"] = calibrated_blocks(rigs.host)
        base = plan or (Plan.quick() if quick else Plan())
        fitted = base.fitted(rigs.start_s_mm(), rigs.home_switch_mm(), rigs.travel_mm())
        snapshots = await _experiments(rigs, world, fitted, link, seed, results)
    finally:
        await world.stop()
    camera = rigs.host_camera()
    results["calibration"] = parameter_errors(rigs.host, rigs.truth)
    home = results.get("home", {})
    if home.get("truth") is not None:  # the zero's truth is the plant's, not the drawing's
        results["calibration"]["track.home_mm"].update(home)
    results["propagation"] = propagation_results(camera, samples=20_000 if quick else 100_000)
    results["report"] = str(write_report(out_dir, results, snapshots, sc))
    return results


async def _experiments(
    rigs: DemoRigs, world: SimWorld, plan: Plan, link: str, seed: int, results: dict[str, Any]
) -> list[tuple[str, Any]]:
    """Static, moving and drift experiments on the host's rig; results in place; snapshots."""
    start_s = rigs.start_s_mm()
    rig, camera, model = rigs.host_kinematics(), rigs.host_camera(), model_of(rigs.host)
    host_pose, true_pose = rigs.host_workpiece(), rigs.true_workpiece()
    robot = MovingRobot(
        host_pose, rig.track.pose(start_s)[:3, 0], plan.moving_speed_mm_s, plan.moving_length_mm
    )
    phase = {"static": True}

    def workpiece(t_ns: int) -> np.ndarray:
        return host_pose if phase["static"] else robot.pose_at_ns(t_ns)

    def true_workpiece(t_ns: int) -> np.ndarray:
        return true_pose if phase["static"] else robot.pose_at_ns(t_ns, true_pose)

    progress = Progress({"connect": 1, "static": 5, "moving": 2, "drift": 5})
    ctrl = Controller(world.host_transport())
    scene = build_scene(rigs.host)
    rf = rigs.host.rangefinder
    ranger = rig_references.ranger(rigs.host, rig)  # the references with the rig file's σ
    pitch = world.sim.scenario.chain.pitch_mm
    feed = TrackFeed(rigs.host.track.marks.s_mm, pitch, ranger, chain_config(rigs.host, pitch))
    ctrl.add_sink(feed)
    ranges = RangeTap()
    ctrl.add_sink(ranges)
    bench = Bench(
        ctrl,
        rig,
        camera,
        model,
        feed,
        workpiece,
        Truth(rigs.true_kinematics(), rigs.true_camera()),
        home_switch_s_mm=rigs.home_switch_mm(),
        latency_ns=round(rigs.host.camera.latency.value * 1e6),
        home_survey_sigma_mm=SURVEY_SIGMA_MM,
        ranges=ranges,
        scene=scene,
        range_noise_mm=rf.noise_mm,
        # without tolerances the host computes with the truth, not with the file's σ: no budget
        predicted_px=_budget(rigs) if rigs.tolerances else None,
    )
    clock = _frame_clock(rigs, seed)
    source = SimCameraSource(
        world, bench.truth.rig, bench.truth.camera, model, true_workpiece,
        fps=rigs.truth.camera.fps, delivery_s=clock.delivery_s, clock=clock,
        render_every=RENDER_EVERY,
    )  # fmt: skip
    loop = FrameLoop(
        SteadyClockSource(source),  # as the daemon's default `[camera] stamps = "steady"`
        bench.process(),
        [bench.collector],
        ready=lambda frame: feed.corrected.covers(frame.exposure_ns - bench.latency_ns),
        max_wait_s=frame_wait_s(LINK_KINDS[link]),
    )
    frames = asyncio.create_task(loop.run())
    lag = LoopLag()
    lag_task = asyncio.create_task(lag.run())
    try:
        progress("connect: handshake and homing", 0.0)
        ident = await ctrl.connect()
        results["controller"] = {"fw_version": ident.fw_version, "boot_id": ident.boot_id}
        results["faults_cleared"] = await start_host(bench, link)
        # A zero surveyed at commissioning is in the rig file, and the calibration that came
        # after it (track placement, workpiece) was solved with it; the same switch and index
        # give the same zero. Otherwise it is surveyed now, by the rangefinder on the end wall.
        surveyed = rigs.host.track.home.provenance.method != NOMINAL
        reference = await survey_home(bench)  # the drift's re-homing is compared with this
        bench.home_reference_mm = (rigs.host.track.home.value if surveyed else reference, reference)
        feed.set_home(bench.home_reference_mm[0])
        if (ranger := feed.corrected.ranger) is not None:  # fixes relative to this survey
            zero = bench.home_reference_mm[0]
            ranger.anchor_at(zero, LOOK_AHEAD_PAN_RAD, LOOK_AHEAD_TILT_RAD, reference)
        await wait_still(bench)
        bench.home_truth_mm = true_zero_mm(world)  # scoring only
        results["home"] = {"estimate": feed.home_s_mm, "truth": bench.home_truth_mm}
        results["static"] = await static_experiment(bench, plan, start_s, progress)
        phase["static"] = False
        results["moving"] = await moving_experiment(bench, plan, start_s, robot, progress)
        source.render = False  # the loop is scored on poses; rendering would only cost frames
        results["drift"] = await drift_experiment(bench, world, plan, progress)
        results["faults_cleared"] += bench.faults_cleared  # recovered from mid-run
        results["link_stats"] = _plain(ctrl.session.stats)
        results["frame_loop"] = {
            "captured": loop.stats.captured,
            "processed": loop.stats.processed,
            "dropped": loop.stats.dropped,
            "timed_out": loop.stats.timed_out,  # registered without all their samples
            "camera_waited_for_plant": source.late_plant,  # the plant's thread ran late
            "latency_ms_median": loop.stats.latency_ms(0.5),
            "latency_ms_p99": loop.stats.latency_ms(0.99),
        }
        results["host_loop_lag_ms_max"] = lag.max_ms
    finally:
        lag_task.cancel()
        loop.stop()
        source.close()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(frames, 10.0)
        await ctrl.close()
        progress.finish()
    return bench.snapshots


async def _commission(rigs: DemoRigs, world: SimWorld, rig_file: Path, seed: int) -> dict[str, Any]:
    """The installer's session through the running daemon (the board in the hall, surveys)."""
    setup = place_board(rigs, seed)
    clock = _frame_clock(rigs, seed)
    true_pose = rigs.true_workpiece()
    camera = SimCameraSource(
        world, rigs.true_kinematics(), rigs.true_camera(), model_of(rigs.truth),
        lambda t_ns: true_pose, fps=COMMISSIONING_FPS, delivery_s=clock.delivery_s,
        clock=clock, board=setup.placed, seed=seed,
    )  # fmt: skip
    targets = feature_points(rigs.truth)

    def stick_targets(on: bool) -> None:
        camera.targets_p = targets if on else None

    session = make_commissioner(setup, seed, _log, stick_targets)
    t0 = time.monotonic()
    try:
        async with running_daemon(world, rig_file, rig_file.parent / "daemon", camera) as daemon:
            report = dict(await session(daemon, rigs, world))
    finally:
        camera.close()
    report["total_s"] = time.monotonic() - t0
    return report


def calibrated_blocks(spec: RigSpec) -> list[str]:
    """The rig file's blocks that a measurement wrote (provenance other than nominal)."""
    blocks = {
        "camera.intrinsics": spec.camera.intrinsics.provenance,
        "head.m_cr": spec.head.m_cr.provenance,
        "track.placement": spec.track.placement.provenance,
        "track.home": spec.track.home.provenance,
        "track.arcs": spec.track.arcs,
        "camera.latency": spec.camera.latency.provenance,
        "rangefinder.mount": spec.rangefinder.mount.provenance,
        "workpiece.frame": spec.workpiece.frame.provenance,
    }
    return [name for name, prov in blocks.items() if prov.method != NOMINAL]


def _budget(rigs: DemoRigs) -> Callable[[float, float, float], float]:
    """The error budget of the host's rig file (cal11's): predicted σ of the model's centre."""
    inputs = inputs_from_rig(rigs.host)
    centre = model_of(rigs.host).vertices.mean(axis=0)[None, :]

    def predicted(s_mm: float, pan: float, tilt: float) -> float:
        return float(overlay_sigma(inputs, s_mm, pan, tilt, centre).sigma_px)

    return predicted


def _log(line: str) -> None:
    """A progress line on stderr."""
    sys.stderr.write(line + "\n")
    sys.stderr.flush()


def _frame_clock(rigs: DemoRigs, seed: int) -> FrameClock:
    """Exposure stamps without tolerances; with them, the true camera's delivery stamps."""
    if not rigs.tolerances or rigs.truth.camera.trigger:
        return FrameClock(triggered=True)
    # The true latency is the stamps' mean offset: delivery plus the jitter's mean |N(0, σ)|.
    jitter_s = Tolerances().latency_jitter_ms / 1e3
    mean_late_s = rigs.truth.camera.latency.value / 1e3
    delivery_s = mean_late_s - jitter_s * math.sqrt(2 / math.pi)
    return FrameClock(delivery_s=delivery_s, jitter_s=jitter_s, seed=seed)


def _plain(stats: object) -> dict[str, Any]:
    """A stats dataclass as plain numbers."""
    return {k: v for k, v in vars(stats).items() if isinstance(v, int | float)}


def add_parser(subparsers: Any) -> None:
    """Register `orbitar demo`."""
    demo = subparsers.add_parser(
        "demo", help="run the paper's experiments on the built-in simulator, write a report"
    )
    demo.add_argument(
        "--quick", action="store_true", help="a shorter run (about 2 min with commissioning)"
    )
    demo.add_argument(
        "--link",
        choices=("pty", "xbee", "can"),
        default="pty",
        help="how the daemon reaches the emulated controller (default: pty)",
    )
    demo.add_argument(
        "--out",
        type=Path,
        default=Path("orbitar-report"),
        help="report directory (default: ./orbitar-report)",
    )
    demo.add_argument("--seed", type=int, default=1, help="simulator seed")
    demo.add_argument(
        "--rig",
        type=Path,
        default=None,
        help="rig file to simulate (default: the paper's rig in a surveyed hall)",
    )
    demo.add_argument(
        "--tolerances",
        choices=("off", "on"),
        default="on",
        help="on (default): the simulated rig is off its description by seeded installation "
        "tolerances and the host starts from the description only, so the demo commissions it "
        "first; off: the host is handed the simulated rig (registration figures without "
        "calibration error)",
    )
    demo.add_argument(
        "--commission",
        choices=("auto", "on", "off"),
        default="auto",
        help="commission through the daemon first (auto: when --tolerances on)",
    )
    demo.add_argument("--ui", action="store_true", help="serve the live AR station until Ctrl-C")
    demo.add_argument("--ui-host", default="127.0.0.1", help="station address (with --ui)")
    demo.add_argument("--ui-port", type=int, default=8080, help="station port (with --ui)")
    demo.set_defaults(handler=main)


def main(args: Any) -> int:
    """Run the demo and print the summary and the report's path."""
    from host.demo.report_pages import summary_text

    if args.ui:
        from host.station.newcomer import main as station_demo

        return station_demo(args)
    tolerances = args.tolerances == "on"
    commission = args.commission == "on" or (args.commission == "auto" and tolerances)
    try:
        results = asyncio.run(
            run_demo(args.link, args.quick, args.out, args.seed, args.rig, tolerances, commission)
        )
    except RigError as exc:
        for problem in exc.problems:
            print(f"orbitar demo: {problem}", file=sys.stderr)
        return 2
    except (LinkError, MotionFailed, TimeoutError) as exc:
        print(f"orbitar demo: the run stopped: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    print(summary_text(results))
    print(f"Report: {results['report']}")
    return 0
