"""Driving the rig for a commissioning run: go to a planned view, wait until still, take a frame.

Every motion goes through the daemon's controller, like any operator command; before each one
the run checks the controller's state, and a latched e-stop or fault ends the run at once (a STOP
also cancels the run: host/commissioning/jobs.py). "Still" means the trolley is within
`POSITION_TOL_MM` of its target and READY, the head's reported angles are within
`HEAD_TOL_RAD` of the command, `HEAD_SETTLE_S` has passed since the head got there and
`SETTLE_S` since the trolley did, for the ring-down after a trolley move (the rotor on its chain
rings at ~14 Hz, ζ ≈ 0.2: 0.3 s is five time constants; it rings down while the head turns);
the frame taken is one stamped after that, plus a margin for a camera that stamps at delivery.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from host.commissioning.frames import FrameTap, wait_frame
from host.commissioning.plan import ViewTarget
from host.control.api import ControllerLike
from host.frames.sources import Frame
from host.geometry.transforms import FloatArray, angle_median

POSITION_TOL_MM = 0.5
HEAD_TOL_RAD = 2e-3
SETTLE_S = 0.3
HEAD_SETTLE_S = 0.15
POLL_S = 0.02
MOVE_TIMEOUT_S = 60.0
HEAD_TIMEOUT_S = 15.0
FRAME_TIMEOUT_S = 5.0
SAME_SAMPLE_S = 0.002  # two polls whose head sample is this close in time read the same one
STAMP_MARGIN_S = 0.1  # a frame stamped this long after rest was exposed after it, even at delivery
TRAVEL_SPEED_MM_S = 500.0  # the controller's MAX_SPEED default
HALTED_STATES = ("ESTOP", "FAULT")


class AbortedError(RuntimeError):
    """The rig cannot carry on (e-stop, fault, link down, not homed, a timeout)."""


@dataclass
class RestReadings:
    """The head's angles while it stands, one per head sample: polls outpace the head's
    telemetry (10-50 Hz), and a sample read twice would weigh twice in its noise and in a
    median of neighbours. Every poll counts where the snapshot gives no `head_age_s`."""

    readings: list[tuple[float, float]] = field(default_factory=list)
    _last_sample_s: float = field(default=math.nan, init=False, repr=False)

    def take(self, snap: Mapping[str, Any], now_s: float) -> None:
        """One poll's snapshot, taken at monotonic `now_s`."""
        head, age = snap.get("head_rad"), snap.get("head_age_s")
        if not head:
            return
        if age is not None:
            sample_s = now_s - float(age)
            if abs(sample_s - self._last_sample_s) < SAME_SAMPLE_S:
                return
            self._last_sample_s = sample_s
        self.readings.append((float(head[0]), float(head[1])))


@dataclass
class RigIO:
    """Motion and frames for a run, on the daemon's controller and camera."""

    controller: ControllerLike
    frames: FrameTap
    speed_mm_s: float = TRAVEL_SPEED_MM_S
    settle_s: float = SETTLE_S
    head_settle_s: float = HEAD_SETTLE_S
    home_s_mm: float = 0.0  # plans speak track arc length; the controller, its own zero
    # the head's readings (n, 2) while it stood waiting for the last frame grabbed
    rest_head_rad: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))

    def s_mm(self, snap: Mapping[str, Any]) -> float | None:
        """Track arc length of the trolley in a snapshot (encoder plus the surveyed home)."""
        pos = snap.get("position_mm")
        return None if pos is None else float(pos) + self.home_s_mm

    def snapshot(self) -> Mapping[str, Any]:
        """The controller's state; AbortedError if motion must not go on."""
        if not self.controller.connected:
            raise AbortedError("the controller link is down")
        snap = self.controller.snapshot()
        state = str(snap.get("state", "UNKNOWN"))
        if state in HALTED_STATES:
            raise AbortedError(f"controller is in {state}")
        return snap

    async def go(self, view: ViewTarget) -> None:
        """Trolley to the view's station (if not there), head to its angles, then settle."""
        target = view.s_mm - self.home_s_mm  # plans speak arc length, the controller its zero
        position = self.snapshot().get("position_mm")
        moving = position is None or abs(float(position) - target) > POSITION_TOL_MM
        rest_s = 0.0  # monotonic time from which the trolley has rung down
        if moving:
            await self.controller.move_to(target, self.speed_mm_s)
            where = f"trolley to s = {view.s_mm:.0f} mm"
            await self._until(lambda s: _at(s, target), MOVE_TIMEOUT_S, where)
            rest_s = time.monotonic() + self.settle_s
        self.snapshot()
        # Not while travelling: with the head turning as the trolley ran, the daemon's pose
        # source read the following passes 9-16 % slow (seed 1), failing calibrate_latency.
        await self.controller.set_head(view.pan_rad, view.tilt_rad)
        await self._until(lambda s: _head_at(s, view), HEAD_TIMEOUT_S, "head to its angles")
        rest_s = max(rest_s, time.monotonic() + self.head_settle_s)
        await asyncio.sleep(rest_s - time.monotonic())

    async def grab(self) -> Frame:
        """A frame exposed after the rig came to rest; the head's samples while it stood
        waiting for it are kept in `rest_head_rad` (its read noise: commissioning.head_noise),
        each once where the snapshot says how old its head sample is."""
        after_ns = time.monotonic_ns() + round(STAMP_MARGIN_S * 1e9)
        rest = RestReadings()

        def read_head() -> None:
            rest.take(self.controller.snapshot(), time.monotonic())

        frame = await wait_frame(self.frames, after_ns, FRAME_TIMEOUT_S, read_head)
        self.rest_head_rad = np.array(rest.readings, dtype=np.float64).reshape(-1, 2)
        return frame

    def head_at_rest(self, snap: Mapping[str, Any]) -> tuple[float, float]:
        """The head's angles for the frame last grabbed: the median of its readings while it
        stood (an angle encoder at rest flickers a count now and then: one reading can be a
        count off, 0.3 mm at 3 m on the simulated head), else the snapshot's (nan if none)."""
        if len(self.rest_head_rad):
            pan, tilt = angle_median(self.rest_head_rad)  # the pan's stop may sit at ±π
            return float(pan), float(tilt)
        head = snap.get("head_rad") or (math.nan, math.nan)
        return float(head[0]), float(head[1])

    async def _until(self, ok: Any, timeout_s: float, what: str) -> None:
        """Poll the snapshot until ok(snapshot); AbortedError on halt or timeout."""
        deadline = time.monotonic() + timeout_s
        while not ok(self.snapshot()):
            if time.monotonic() > deadline:
                raise AbortedError(f"{what}: not reached within {timeout_s:.0f} s")
            await asyncio.sleep(POLL_S)


def _at(snap: Mapping[str, Any], s_mm: float) -> bool:
    """Trolley at rest at s_mm."""
    pos = snap.get("position_mm")
    return (
        pos is not None
        and abs(float(pos) - s_mm) <= POSITION_TOL_MM
        and snap.get("state") == "READY"
    )


def _head_at(snap: Mapping[str, Any], view: ViewTarget) -> bool:
    """Head angles reported within tolerance of the view's."""
    head = snap.get("head_rad")
    if not head:
        return False
    dp = math.remainder(float(head[0]) - view.pan_rad, math.tau)
    dt = math.remainder(float(head[1]) - view.tilt_rad, math.tau)
    return abs(dp) <= HEAD_TOL_RAD and abs(dt) <= HEAD_TOL_RAD
