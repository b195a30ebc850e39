"""A rig in a surveyed hall and a true rig drawn around it, for the rangefinder runs' tests.

The truth is drawn from the σ the rig file states (mount, placement, each wall's survey) plus a
shift of the arc length (an unsurveyed home), so a run that reports a σ it does not achieve
fails the 3σ checks. Readings come from `host.geometry.rangefinder.range_at` on the true rig and
the true walls: the same model, other numbers.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from host.commissioning.env import CommissioningEnv
from host.commissioning.frames import RangeTap
from host.commissioning.range_model import local
from host.config import Config, ControlConfig
from host.control.client import ControlClient
from host.geometry.head import Rig
from host.geometry.rangefinder import RangeScene, Surface, hall_walls, range_at
from host.rig import (
    HallSpec,
    Marks,
    Pose6,
    RigSpec,
    Scalar,
    SurfaceSpec,
    build_kinematics,
    build_scene,
    save_rig,
)
from host.service.daemon import Daemon
from tests.fakes import MemoryController, MemoryFrameLoop

HALL_X_MM, HALL_Y_MM = (-6000.0, 6000.0), (-4500.0, 4500.0)
MARKS_MM = tuple(float(s) for s in np.arange(400.0, 16_200.0, 1000.0))
TRUE_MOUNT_MM, TRUE_MOUNT_RAD = 2.0, 3e-3  # the simulator's tolerance (hil_sim.true_rig)


def hall_rig(
    mount_sigma: tuple[float, float] | None = None,
    placement_sigma: tuple[float, float] | None = None,
    marks_mm: tuple[float, ...] = MARKS_MM,
) -> RigSpec:
    """The paper's runway in a 12 m × 9 m hall, walls and floor surveyed to 1 mm, the head able
    to look at the horizon; optionally a mount and placement already calibrated to (mm, rad)."""
    base = RigSpec()
    hall = HallSpec(
        tuple(SurfaceSpec(s.name, s.point_w, s.normal_w, 0.0, 1.0)
              for s in hall_walls(HALL_X_MM, HALL_Y_MM))
    )  # fmt: skip
    spec = dataclasses.replace(
        base,
        hall=hall,
        head=dataclasses.replace(base.head, tilt_max_rad=math.pi / 2),
        track=dataclasses.replace(base.track, marks=Marks(marks_mm)),
    )
    if mount_sigma is not None:
        mm, rad = mount_sigma
        mount = Pose6(spec.rangefinder.mount.matrix, (rad,) * 3, (mm,) * 3)
        rf = dataclasses.replace(spec.rangefinder, mount=mount)
        spec = dataclasses.replace(spec, rangefinder=rf)
    if placement_sigma is not None:
        mm, rad = placement_sigma
        placement = Pose6(spec.track.placement.matrix, (rad,) * 3, (mm,) * 3)
        spec = dataclasses.replace(spec, track=dataclasses.replace(spec.track, placement=placement))
    return spec


@dataclass(frozen=True)
class Truth:
    """The built rig: kinematics, walls, the true arc length of a host arc length, true marks."""

    rig: Rig
    scene: RangeScene
    shift_mm: float  # true arc length = host arc length + shift
    marks_mm: tuple[float, ...]  # true arc lengths of the marks

    def reading(self, s_host: float, pan: float, tilt: float) -> float | None:
        """The noiseless distance the rangefinder reads."""
        hit = range_at(self.rig, self.scene, s_host + self.shift_mm, pan, tilt)
        return None if hit is None else hit.distance_mm


def draw_truth(spec: RigSpec, rng: np.random.Generator, mount_from_spec: bool = False,
               shift_sigma_mm: float = 5.0) -> Truth:  # fmt: skip
    """A true rig around `spec`: mount off by the simulator's tolerance (or by the spec's σ),
    placement by the spec's covariance, each surface by its survey σ, marks by 1 mm."""
    if mount_from_spec:
        d_m = np.linalg.cholesky(spec.rangefinder.mount.cov()) @ rng.normal(size=6)
    else:
        d_m = np.r_[rng.normal(0, TRUE_MOUNT_RAD, 3), rng.normal(0, TRUE_MOUNT_MM, 3)]
    d_p = np.linalg.cholesky(spec.track.placement.cov()) @ rng.normal(size=6)
    rig = build_kinematics(spec)
    rig = dataclasses.replace(
        rig,
        T_r_l=local(spec.rangefinder.mount.matrix, d_m),
        track=rig.track.with_origin(local(spec.track.placement.matrix, d_p)),
    )
    scene = build_scene(spec)
    assert scene is not None
    walls = []
    for s, survey in zip(scene.surfaces, spec.hall.surfaces, strict=True):
        p = np.asarray(s.point_w) + np.asarray(s.normal_w) * rng.normal(0, survey.sigma_mm)
        walls.append(Surface(s.name, (float(p[0]), float(p[1]), float(p[2])), s.normal_w))
    marks = tuple(float(m) + rng.normal(0, 1.0) for m in spec.track.marks.s_mm)
    return Truth(rig, RangeScene(tuple(walls)), float(rng.normal(0, shift_sigma_mm)), marks)


class TrueSensors:
    """The true rig's mark sensor and rangefinder on a fake controller: each mark's capture (the
    controller's position at its edge) and a reading every 10 ms (noise from the rig file)."""

    def __init__(self, controller: Any, truth: Truth, home_mm: float, tap: RangeTap,
                 noise_mm: float, seed: int) -> None:  # fmt: skip
        self.controller, self.truth, self.home_mm, self.tap = controller, truth, home_mm, tap
        self.noise_mm = noise_mm
        self.rng = np.random.default_rng(seed)

    def true_s(self, position_mm: float) -> float:
        return position_mm + self.home_mm + self.truth.shift_mm

    async def run(self) -> None:
        last = self.true_s(self.controller.position_mm)
        tick = 0
        while True:
            await asyncio.sleep(0.002)
            now = time.monotonic_ns()
            s = self.true_s(self.controller.position_mm)
            for m in self.truth.marks_mm:
                if min(last, s) < m <= max(last, s):
                    self.tap.on_mark(now, m - self.home_mm - self.truth.shift_mm)
            last = s
            tick += 1
            if tick % 5:
                continue
            d = self.truth.reading(s - self.truth.shift_mm, *self.controller.head_rad)
            if d is not None:
                self.tap.on_range(now, d + float(self.rng.normal(0, self.noise_mm)), 1)


@dataclass
class Bench:
    """A daemon on a fake controller with the true rig's sensors, and its rig file."""

    client: ControlClient
    controller: Any
    rig_path: Path
    report_root: Path
    truth: Truth


@asynccontextmanager
async def sensed_daemon(tmp: Path, spec: RigSpec, truth: Truth, home_mm: float,
                        seed: int) -> AsyncIterator[Bench]:  # fmt: skip
    """A daemon reading `spec` (written as its rig file), homed, serving its control socket."""
    rig_path = tmp / "rig.toml"
    track = dataclasses.replace(spec.track, home=Scalar(home_mm, 1.0))
    save_rig(dataclasses.replace(spec, track=track), rig_path)
    fake = MemoryController()
    env = CommissioningEnv.for_rig_file(rig_path, lambda: None, tmp / "reports")
    tap = RangeTap()
    env.ranges = lambda: tap
    sensors = asyncio.create_task(
        TrueSensors(fake, truth, home_mm, tap, spec.rangefinder.noise_mm, seed).run()
    )
    sock = tmp / "ctl.sock"
    config = dataclasses.replace(
        Config(),
        control=ControlConfig(socket_path=str(sock)),
        rig=dataclasses.replace(Config().rig, path=str(rig_path)),
    )
    loop = lambda c, ctl, sink, t: MemoryFrameLoop(fake, sink)  # noqa: E731
    daemon = Daemon(config, lambda c, t: fake, loop, commissioning=env)
    task = asyncio.create_task(daemon.run())
    try:
        for _ in range(250):
            if sock.exists() and fake.connected:
                break
            await asyncio.sleep(0.02)
        async with await ControlClient.connect_unix(str(sock)) as client:
            await client.request("home")
            yield Bench(client, fake, rig_path, tmp / "reports", truth)
    finally:
        sensors.cancel()
        daemon.request_stop()
        await asyncio.wait_for(task, 10.0)
