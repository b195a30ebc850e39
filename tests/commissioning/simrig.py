"""A daemon on a fake controller whose camera renders a board through a seeded true rig."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil_sim.camera import FrameClock, PlacedBoard, SyntheticCamera
from host.calibration.board import BoardSpec
from host.commissioning.env import CommissioningEnv
from host.commissioning.frames import FrameTap, RangeTap
from host.config import Config, ControlConfig
from host.config_ui import UiConfig
from host.control.client import ControlClient
from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.rangefinder import RangeScene, hall_walls
from host.geometry.transforms import euler_zyx, make_T, rot_x
from host.rig import HallSpec, RigSpec, Scalar, SurfaceSpec, save_rig
from host.service.daemon import Daemon
from tests.fakes import MemoryController as FakeController

FPS = 15.0
BOARD = BoardSpec(squares_x=8, squares_y=6, square_mm=70.0, marker_mm=52.0)
# On a stand 1.5 m above the floor, 0.4 m inside the runway's first straight (camera 4 m up).
BOARD_CENTRE_W = np.array([-300.0, -1100.0, 1500.0])
STATIONS_MM = [1700.0, 3000.0]


def true_lens(rng: np.random.Generator) -> CameraModel:
    """A lens off Table 1 by manufacturing tolerances."""
    base = CameraModel()
    return dataclasses.replace(
        base,
        fx=base.fx * (1 + rng.normal(0, 0.01)), fy=base.fy * (1 + rng.normal(0, 0.01)),
        u0=base.u0 + rng.normal(0, 5), v0=base.v0 + rng.normal(0, 5),
        skew=base.skew + rng.normal(0, 0.3), k1=base.k1 + rng.normal(0, 0.1),
        k2=base.k2 + rng.normal(0, 0.3),
    )  # fmt: skip


def true_rig(rng: np.random.Generator) -> Rig:
    """The nominal rig with M_cr off by a few mm and mrad."""
    nominal = Rig()
    dR = euler_zyx(*rng.normal(0, 3e-3, 3))
    M = nominal.T_r_c.copy()
    M[:3, :3] = M[:3, :3] @ dR
    M[:3, 3] += rng.normal(0, 3.0, 3)
    return Rig(track=nominal.track, T_r_c=M)


def board_pose(rng: np.random.Generator) -> np.ndarray:
    """The board face up (toward the camera above), turned a little, where the plan expects it."""
    R = rot_x(np.pi) @ euler_zyx(rng.uniform(-0.3, 0.3), rng.normal(0, 0.05), rng.normal(0, 0.05))
    return make_T(R, BOARD_CENTRE_W - R @ BOARD.centre_mm)


@dataclass
class SimBoardLoop:
    """The daemon's frame loop: renders what the true camera sees, stamped at delivery."""

    controller: FakeController
    rig: Rig
    camera: SyntheticCamera
    board: PlacedBoard
    clock: FrameClock
    blur_mm: float = 0.0  # smear every frame by this much camera motion (a shaking mount)
    home_s_mm: float = 0.0  # true arc length of the controller's zero
    frame_tap: FrameTap = field(init=False)
    frames: int = 0

    def __post_init__(self) -> None:
        self.frame_tap = FrameTap(self)

    @property
    def fps(self) -> float:
        return FPS

    def read(self) -> None:
        return None

    def close(self) -> None:
        return None

    async def run(self) -> None:
        while True:
            exposed_ns = time.monotonic_ns()
            s = self.controller.position_mm + self.home_s_mm
            pan, tilt = self.controller.head_rad
            image = await asyncio.to_thread(self._render, s, pan, tilt)
            self.frames += 1
            stamp = self.clock.stamp_ns(exposed_ns)
            await asyncio.sleep(max(0.0, (stamp - time.monotonic_ns()) / 1e9))
            self.frame_tap.offer(Frame(self.frames, image, stamp, (s, pan, tilt)))
            await asyncio.sleep(1.0 / FPS)

    def _render(self, s: float, pan: float, tilt: float) -> np.ndarray:
        T_w_c = self.rig.T_w_c(s, pan, tilt)
        T_c_b = np.linalg.inv(T_w_c) @ self.board.T_w_b
        end = None
        if self.blur_mm:
            end = T_c_b.copy()
            end[0, 3] += self.blur_mm
        return self.camera.render_board(T_c_b, self.board.board, end).image


class PoseRecorder:
    """The host's view of the fake trolley over time (an encoder buffer at 500 Hz)."""

    def __init__(self, controller: FakeController, home_s_mm: float) -> None:
        self.controller, self.home_s_mm = controller, home_s_mm
        self.t: list[int] = []
        self.rows: list[tuple[float, float, float]] = []

    async def run(self) -> None:
        while True:
            pan, tilt = self.controller.head_rad
            self.t.append(time.monotonic_ns())
            self.rows.append((self.controller.position_mm + self.home_s_mm, pan, tilt))
            del self.t[:-5000], self.rows[:-5000]
            await asyncio.sleep(0.002)

    def pose_at(self, t_ns: int) -> tuple[float, float, float] | None:
        """Linear interpolation between the recorded samples (None outside them)."""
        if len(self.t) < 2 or not self.t[0] <= t_ns <= self.t[-1]:
            return None
        i = max(int(np.searchsorted(self.t, t_ns)), 1)
        f = (t_ns - self.t[i - 1]) / max(self.t[i] - self.t[i - 1], 1)
        a, b = np.array(self.rows[i - 1]), np.array(self.rows[i])
        s, pan, tilt = a + f * (b - a)
        return float(s), float(pan), float(tilt)


MODEL_FEATURES_P = np.array(
    [[0, 0, 0], [400, 0, 200], [0, 300, 600], [-200, 250, 900], [0, 0, 1200]], dtype=np.float64
)


FEATURE_RADIUS_MM = 30.0
HOME_MM = 150.0  # the home switch's arc length in the rig file (surveyed, σ 1 mm)
HALL_X_MM, HALL_Y_MM = (-6000.0, 6000.0), (-4500.0, 4500.0)
# the hall as built: its survey (the rig file) is within a millimetre of it
TRUE_HALL = RangeScene(hall_walls((HALL_X_MM[0] + 0.4, HALL_X_MM[1] - 0.3), HALL_Y_MM))


def surveyed_hall() -> HallSpec:
    """The rig file's survey of the hall's walls."""
    return HallSpec(
        tuple(SurfaceSpec(w.name, w.point_w, w.normal_w) for w in hall_walls(HALL_X_MM, HALL_Y_MM))
    )


class FakeRangefinder:
    """Readings at 100 Hz along the true beam to the feature it points at (1 mm noise)."""

    def __init__(self, loop: SimBoardLoop, T_w_p: np.ndarray, tap: RangeTap, seed: int) -> None:
        self.loop, self.tap = loop, tap
        self.points_w = MODEL_FEATURES_P @ T_w_p[:3, :3].T + T_w_p[:3, 3]
        self.rng = np.random.default_rng(seed)

    async def run(self) -> None:
        while True:
            c = self.loop.controller
            s = c.position_mm + self.loop.home_s_mm
            T = self.loop.rig.T_w_r(s, *c.head_rad) @ self.loop.rig.T_r_l
            o, z = T[:3, 3], T[:3, 2]
            # a feature on the beam (a surface there), else the hall's walls
            off = self.points_w - o
            lateral = np.linalg.norm(off - np.outer(off @ z, z), axis=1)
            hit = TRUE_HALL.cast(o, z)
            if lateral.min() < FEATURE_RADIUS_MM:
                d = float(off[int(np.argmin(lateral))] @ z)
            elif hit is not None:
                d = hit.distance_mm
            else:
                await asyncio.sleep(0.01)
                continue
            self.tap.on_range(time.monotonic_ns(), d + float(self.rng.normal(0.0, 1.0)), 1)
            await asyncio.sleep(0.01)


@dataclass
class Harness:
    """A running daemon, its client, the truth and the rig file."""

    daemon: Daemon
    client: ControlClient
    loop: SimBoardLoop
    lens: CameraModel
    rig: Rig
    rig_path: Path
    report_root: Path
    workpiece: np.ndarray  # the true T_w_p (scoring only)

    async def request(self, op: str, **args: Any) -> Any:
        return await self.client.request(op, **args)

    async def budget_at(self, pan: float, tilt: float, timeout_s: float = 10.0) -> Any:
        """The status' service part once its error budget is of these head angles and the head
        has settled there (the daemon evaluates it in the background at the pose it reports;
        a value of a pose the head was still passing would be replaced by a later one).

        Settled: the controller's head is at the angles, the evaluated pose (trolley and head)
        is the controller's as it stands, and two polls in a row give the same σ."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        previous = None
        while True:
            status = await self.request("status")
            service, ctrl = status["service"], status["controller"]
            at, head = service["overlay_sigma_pose"], ctrl["head_rad"]
            here = at is not None and abs(head[0] - pan) + abs(head[1] - tilt) < 2e-3
            if (
                here
                and abs(at["pan_rad"] - head[0]) + abs(at["tilt_rad"] - head[1]) < 1e-4
                and abs(at["position_mm"] - ctrl["position_mm"]) < 0.1
            ):
                if previous is not None and previous == service["overlay_sigma_px"]:
                    return service
                previous = service["overlay_sigma_px"]
            else:
                previous = None
            if asyncio.get_running_loop().time() > deadline:
                raise AssertionError(f"no error budget at pan {pan}, tilt {tilt}: {service}")
            await asyncio.sleep(0.05)


@asynccontextmanager
async def sim_daemon(
    tmp: Path, seed: int, blur_mm: float = 0.0, ui: UiConfig | None = None
) -> AsyncIterator[Harness]:
    """A daemon on the fake controller with the rendered board (and `ui`'s station, if given)."""
    rng = np.random.default_rng(seed)
    lens, rig = true_lens(rng), true_rig(rng)
    placed = PlacedBoard(BOARD.make(), board_pose(rng))
    fake = FakeController()
    sim = SyntheticCamera(lens, seed=seed, blur_samples=4)
    # where the home switch truly is: the rig file's survey, off by its σ
    home = HOME_MM + float(rng.normal(0.0, 0.3))
    loop = SimBoardLoop(fake, rig, sim, placed, FrameClock(seed=seed), blur_mm, home)
    rig_path = tmp / "rig.toml"
    nominal = RigSpec()
    track = dataclasses.replace(nominal.track, home=Scalar(HOME_MM, 1.0))
    save_rig(dataclasses.replace(nominal, hall=surveyed_hall(), track=track), rig_path)
    env = CommissioningEnv.for_rig_file(rig_path, lambda: loop.frame_tap, tmp / "reports")
    recorder = PoseRecorder(fake, env.home_s_mm())
    env.pose_at = recorder.pose_at
    recording = asyncio.create_task(recorder.run())
    true_T_w_p = make_T(
        euler_zyx(*rng.normal(0, 0.01, 3)), np.array([-300.0, -300.0, 0.0]) + rng.normal(0, 5.0, 3)
    )
    ranges = RangeTap()
    env.ranges = lambda: ranges
    ranging = asyncio.create_task(FakeRangefinder(loop, true_T_w_p, ranges, seed).run())
    config = dataclasses.replace(
        Config(), control=ControlConfig(socket_path=str(tmp / "ctl.sock")), ui=ui or UiConfig()
    )
    daemon = Daemon(config, lambda c, t: fake, lambda c, ctl, sink, t: loop, commissioning=env)
    task = asyncio.create_task(daemon.run())
    try:
        for _ in range(200):
            if (tmp / "ctl.sock").exists():
                break
            await asyncio.sleep(0.02)
        async with await ControlClient.connect_unix(str(tmp / "ctl.sock")) as client:
            yield Harness(daemon, client, loop, lens, rig, rig_path, tmp / "reports", true_T_w_p)
    finally:
        recording.cancel()
        ranging.cancel()
        daemon.request_stop()
        await asyncio.wait_for(task, 10.0)
