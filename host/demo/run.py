"""`orbitar demo`: the paper's experiments end to end on the simulator, and a report.

The emulator (firmware mirror + plant) runs in real time behind a real link; the daemon's own
controller, pose buffers, frame loop and registration run against it exactly as on a rig.
"""

from __future__ import annotations

import asyncio
import contextlib
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil_sim.scenario import RangefinderConfig, Scenario, TrackConfig
from hil_sim.surveyed_range import surveyed_target
from host.demo.experiments import (
    Bench,
    MovingRobot,
    Plan,
    drift_experiment,
    moving_experiment,
    start_host,
    static_experiment,
    survey_home,
)
from host.demo.feeds import TrackFeed
from host.demo.propagation_report import propagation_results
from host.demo.report_pages import write_report
from host.demo.world import SimCameraSource, SimWorld
from host.frames.loop import FrameLoop
from host.fusion.range_fix import RangeFixConfig, RangeFixer
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import manipulator_wireframe
from host.geometry.rangefinder import RangeScene, hall_walls
from host.geometry.transforms import make_T
from host.link import Controller, LinkError
from host.link.controller import MotionFailed

BAR_WIDTH = 30
START_S_MM = 500.0  # where the trolley stands at power-on (the scenario's default)
MARK_SPACING_MM = 1000.0  # reference marks along the track (magnets under a hall sensor)
FIRST_MARK_MM = 400.0  # just past the home switch, so the chain scale is learnt early
WORKPIECE_W = (-300.0, -300.0, 0.0)  # the robot's base on the floor, inside the runway
# A 12 m × 9 m hall around the runway (6 m × 3 m, centred on the world origin): its walls are
# surveyed, so a rangefinder reading of one is an absolute reference of the track position.
HALL = RangeScene(hall_walls(x_mm=(-6000.0, 6000.0), y_mm=(-4500.0, 4500.0)))


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


def scenario(seed: int, rig: Rig) -> Scenario:
    """The paper's rig in a hall with surveyed walls, reference marks every metre."""
    marks = tuple(np.arange(FIRST_MARK_MM, 16_200.0, MARK_SPACING_MM).tolist())
    return Scenario(
        seed=seed,
        track=TrackConfig(reference_marks_mm=marks),
        rangefinder=RangefinderConfig(target=surveyed_target(rig, HALL)),
    )


async def run_demo(link: str, quick: bool, out_dir: Path, seed: int = 1) -> dict[str, Any]:
    """Run everything; return the results (also written to out_dir)."""
    plan = Plan.quick() if quick else Plan()
    rig, camera, model = Rig(), CameraModel(), manipulator_wireframe()
    sc = scenario(seed, rig)
    world = SimWorld(sc, link)
    static_pose = make_T(np.eye(3), np.array(WORKPIECE_W))
    robot = MovingRobot(
        make_T(np.eye(3), np.array(WORKPIECE_W)),
        rig.track.pose(START_S_MM)[:3, 0],
        plan.moving_speed_mm_s,
        plan.moving_length_mm,
    )
    phase = {"static": True}

    def workpiece(t_ns: int) -> np.ndarray:
        return static_pose if phase["static"] else robot.pose_at_ns(t_ns)

    progress = Progress({"connect": 1, "static": 5, "moving": 2, "drift": 5})
    await world.start()
    ctrl = Controller(world.host_transport())
    ranger = RangeFixer(rig, HALL, RangeFixConfig(noise_mm=sc.rangefinder.noise_mm))
    feed = TrackFeed(sc.track.reference_marks_mm, sc.chain.pitch_mm, ranger)
    ctrl.add_sink(feed)
    bench = Bench(ctrl, rig, camera, model, feed, workpiece)
    source = SimCameraSource(world, rig, camera, model, workpiece)
    loop = FrameLoop(source, bench.process(), [bench.collector])
    frames = asyncio.create_task(loop.run())
    lag = LoopLag()
    lag_task = asyncio.create_task(lag.run())
    results: dict[str, Any] = {"link": link, "quick": quick, "seed": seed}
    try:
        progress("connect: handshake and homing", 0.0)
        ident = await ctrl.connect()
        results["controller"] = {"fw_version": ident.fw_version, "boot_id": ident.boot_id}
        await start_host(bench, link)
        feed.set_home(survey_home(bench, world))
        results["static"] = await static_experiment(bench, plan, START_S_MM, progress)
        phase["static"] = False
        results["moving"] = await moving_experiment(bench, plan, START_S_MM, robot, progress)
        source.render = False  # the loop is scored on poses; rendering would only cost frames
        results["drift"] = await drift_experiment(bench, world, plan, progress)
        results["link_stats"] = _plain(ctrl.session.stats)
        results["frame_loop"] = {
            "captured": loop.stats.captured,
            "processed": loop.stats.processed,
            "dropped": loop.stats.dropped,
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
        await world.stop()
        progress.finish()
    results["propagation"] = propagation_results(camera, samples=20_000 if quick else 100_000)
    results["report"] = str(write_report(out_dir, results, bench.snapshots, sc))
    return results


def _plain(stats: object) -> dict[str, Any]:
    """A stats dataclass as plain numbers."""
    return {k: v for k, v in vars(stats).items() if isinstance(v, int | float)}


def add_parser(subparsers: Any) -> None:
    """Register `orbitar demo`."""
    demo = subparsers.add_parser(
        "demo", help="run the paper's experiments on the built-in simulator, write a report"
    )
    demo.add_argument("--quick", action="store_true", help="a shorter run (about 30 s)")
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
    try:
        results = asyncio.run(run_demo(args.link, args.quick, args.out, args.seed))
    except (LinkError, MotionFailed, TimeoutError) as exc:
        print(f"orbitar demo: the run stopped: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    print(summary_text(results))
    print(f"Report: {results['report']}")
    return 0
