"""The simulated rig the demo runs against: firmware mirror + plant behind a real link, a camera.

This is one of the two places host code may import the simulator (the other is `orbitar sim`):
the daemon's own code then talks to it exactly as to a real controller, over a pty (serial or
XBee API) or a CAN bus, and reads frames from the synthetic camera. Ground truth leaves this
module only inside `Frame.truth`, for scoring.
"""

from __future__ import annotations

import math
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, cast

import numpy as np
from numpy.typing import NDArray

from hil_sim.camera import FrameClock, PlacedBoard, SyntheticCamera
from hil_sim.links.can_node import VirtualCanNode
from hil_sim.links.endpoint import SimPortEndpoint
from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.wire_loop import WireLoop
from hil_sim.links.xbee import CONTROLLER_ADDR64, XBeeModule
from hil_sim.plant import Truth
from hil_sim.runner import RealtimeRunner, Simulation
from hil_sim.scenario import Scenario
from host.frames.sources import Frame
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import Wireframe
from host.transport import Transport, create_transport

FloatArray = NDArray[np.float64]
LINKS = ("pty", "xbee", "can")
SERIAL_BAUD = 115200
# A camera hands a frame over after readout and transfer, not at exposure: for the Table 1
# camera's 1280×1024 at 30 fps, about 20 ms. What the frame is stamped with is the FrameClock's
# business: the exposure (a triggered camera, and the demo without tolerances) or the delivery.
CAMERA_DELIVERY_S = 0.020
EXPOSURE_STAMPS = FrameClock(triggered=True)
# The camera exposes on its own steady clock, between the plant's 1 ms ticks: it reads the pose
# at its exposure from the plant's recent history, kept this long, once a tick past it has run.
HISTORY_S = 0.5
HISTORY_MARGIN_S = 0.0015
PLANT_POLL_S = 0.0005


class _Emulator(Protocol):
    """What the demo needs of a link emulator."""

    async def start(self) -> None: ...

    async def stop(self) -> None: ...


@dataclass(frozen=True)
class SceneTruth:
    """Ground truth of one rendered frame (scoring only)."""

    T_w_c: FloatArray
    T_w_p: FloatArray
    s_mm: float
    pan_rad: float
    tilt_rad: float


class SimWorld:
    """Simulation in real time, its link emulator, and a camera that renders the true scene."""

    def __init__(self, scenario: Scenario, link: str = "pty") -> None:
        if link not in LINKS:
            raise ValueError(f"link must be one of {LINKS}, got {link!r}")
        self.link = link
        self.sim = Simulation(scenario)
        self.runner = RealtimeRunner(self.sim)
        self._emulator: _Emulator | None = None
        self._wire: WireLoop | None = None
        self._can_channel = f"orbitar-demo-{uuid.uuid4().hex[:8]}"

    async def start(self) -> None:
        """Start the simulator thread and the link emulator, on a loop of its own
        (`hil_sim.links.wire_loop`: the wire does not wait for the daemon's loop)."""
        self._wire = WireLoop(f"hil-wire-{self.link}")
        self._wire.start()
        self._emulator = await self._wire.run(self._start_emulator())
        self.runner.start()

    async def _start_emulator(self) -> _Emulator:
        """On the wire's loop: the emulator, built and started there."""
        import asyncio

        endpoint = SimPortEndpoint(self.runner.port, asyncio.get_running_loop())
        emulator: Any
        if self.link == "pty":
            emulator = PtyUart(endpoint, baud=SERIAL_BAUD)
        elif self.link == "xbee":
            emulator = XBeeModule(endpoint, api_mode=2)
        else:
            emulator = VirtualCanNode(endpoint, self._can_channel)
        await emulator.start()
        return cast(_Emulator, emulator)

    async def stop(self) -> None:
        """Stop the emulator, its loop and the simulator thread."""
        try:
            if self._emulator is not None and self._wire is not None:
                await self._wire.run(self._emulator.stop())
        finally:  # an emulator that fails to stop still lets its loop and the plant go
            self._emulator = None
            if self._wire is not None:
                self._wire.stop()
                self._wire = None
            self.runner.stop()

    @property
    def emulator(self) -> object:
        """The running link emulator (PtyUart, XBeeModule or VirtualCanNode), None if stopped."""
        return self._emulator

    @property
    def can_channel(self) -> str:
        """The python-can virtual channel of the CAN link."""
        return self._can_channel

    @property
    def link_path(self) -> str:
        """The pty a daemon opens for this link (pty and XBee; empty for CAN)."""
        emu = self._emulator
        return emu.path if isinstance(emu, PtyUart | XBeeModule) else ""

    def host_transport(self) -> Transport:
        """The daemon's transport for this link, configured as on a real rig."""
        emu = self._emulator
        if self.link == "pty" and isinstance(emu, PtyUart):
            return create_transport("serial", url=emu.path, baudrate=SERIAL_BAUD)
        if self.link == "xbee" and isinstance(emu, XBeeModule):
            return create_transport("xbee", url=emu.path, api_mode=2, dest_addr64=CONTROLLER_ADDR64)
        return create_transport("can", interface="virtual", channel=self._can_channel)

    def host_time_ns(self, true_s: float) -> int:
        """Host monotonic time at which the plant was at true time `true_s` (real-time pacing)."""
        return self.runner.wall_ns_at(true_s)

    def true_s_at(self, wall_ns: int) -> float:
        """Plant time due at a host monotonic time (the inverse of `host_time_ns`)."""
        return self.runner.true_s_at(wall_ns)

    def keep_history(self, seconds: float) -> None:
        """Keep the plant's recent pose history (`Plant.truth_at`) over at least `seconds`."""
        ticks = round(seconds / self.sim.dt_s)
        with self.runner.lock:
            current = self.sim.plant.history_ticks
            if ticks > current:
                self.sim.plant.keep_history(ticks)

    def with_truth(self, fn: Callable[[Simulation], Any]) -> Any:
        """Run fn on the simulation under the runner's lock (faults, truth)."""
        with self.runner.lock:
            return fn(self.sim)


class SimCameraSource:
    """The synthetic camera: renders the true scene (true rig, true lens) at the plant's time."""

    def __init__(
        self,
        world: SimWorld,
        rig: Rig,
        camera: CameraModel,
        model: Wireframe,
        workpiece: Callable[[int], FloatArray],
        fps: float = 30.0,
        render: bool = True,
        seed: int = 7,
        delivery_s: float = CAMERA_DELIVERY_S,
        clock: FrameClock = EXPOSURE_STAMPS,
        board: PlacedBoard | None = None,
        render_every: int = 1,
        targets_p: FloatArray | None = None,
    ) -> None:
        self.world = world
        self.board = board  # a calibration board in the hall, rendered with the scene
        self.targets_p = targets_p  # photogrammetry targets stuck on the workpiece (frame p)
        # Registration needs only the frame's stamp: rendering every frame (~0.1-0.3 s of CPU
        # for a noisy 1280x1024 image) would starve the link on a loaded machine.
        self.render_every = render_every
        self.rig = rig
        self.model = model
        self.workpiece = workpiece
        self.period_s = 1.0 / fps
        self.delivery_s = delivery_s
        self.clock = clock
        self.render = render
        self._cam = SyntheticCamera(camera, seed=seed)
        self._blank = np.zeros((2, 2, 3), np.uint8)
        self._index = 0
        self._exposure_s: float | None = None  # plant time of the next exposure
        self.late_plant = 0  # waits for a plant thread that ran behind the wall clock
        self._closed = threading.Event()
        world.keep_history(HISTORY_S)

    def read(self) -> Frame | None:
        """Wait for the next exposure of the camera's clock, then render and deliver it."""
        truth = None
        while truth is None:
            exposure_s = self._next_exposure_s()
            truth = self._truth_at(exposure_s)
            if self._closed.is_set():
                return None
        exposure_ns = self.world.host_time_ns(truth.time_s)
        stamp = self.clock.stamp_ns(exposure_ns)
        T_w_c = self.rig.T_w_c(truth.s_wrapped_mm, truth.pan_rad, truth.tilt_rad)
        T_w_p = self.workpiece(exposure_ns)
        image = self._blank
        if self.render and self._index % self.render_every == 0:
            image = self._cam.render_scene(
                T_w_c, self.model, T_w_p, board=self.board, targets_p=self.targets_p
            ).image
        # Delivered when its stamp says (a triggered camera's frame after its readout).
        deliver_ns = max(stamp, exposure_ns + round(self.delivery_s * 1e9))
        hold_s = (deliver_ns - time.monotonic_ns()) / 1e9
        if hold_s > 0 and self._closed.wait(hold_s):
            return None
        self._index += 1
        scene = SceneTruth(T_w_c, T_w_p, truth.s_mm, truth.pan_rad, truth.tilt_rad)
        return Frame(self._index, image, stamp, scene)

    def _next_exposure_s(self) -> float:
        """Plant time of the next exposure on the camera's grid (the sensor runs on while the
        frames are not read: those are lost)."""
        period = self.period_s
        due_s = self.world.true_s_at(time.monotonic_ns())
        if self._exposure_s is None:
            self._exposure_s = due_s + period
        elif due_s - self._exposure_s > period:
            self._exposure_s += math.ceil((due_s - self._exposure_s) / period) * period
        exposure_s = self._exposure_s
        self._exposure_s += period
        return exposure_s

    def _truth_at(self, exposure_s: float) -> Truth | None:
        """The plant's state at the exposure, from its history once a tick past it has run.

        A plant thread held back by the host's load runs late: wait for it, never take another
        instant's state. None when closed, or when the exposure has left the history (this
        thread was held back longer than it): that frame is lost.
        """
        ready_ns = self.world.host_time_ns(exposure_s + HISTORY_MARGIN_S)
        while True:
            wait_s = (ready_ns - time.monotonic_ns()) / 1e9
            if (wait_s > 0 and self._closed.wait(wait_s)) or self._closed.is_set():
                return None
            truth, plant_s = self.world.with_truth(
                lambda sim: (sim.truth_at(exposure_s), sim.time_s)
            )
            if truth is not None or plant_s >= exposure_s:
                return cast("Truth | None", truth)
            self.late_plant += 1  # not there yet: the plant's thread is behind the wall clock
            ready_ns = time.monotonic_ns() + round(PLANT_POLL_S * 1e9)

    def close(self) -> None:
        """Stop delivering frames."""
        self._closed.set()
