"""In-memory doubles of the controller surface and the frame loop, for service-level tests.

`MemoryController` implements `host.control.api.ControllerLike` (the public surface of
`host.link.Controller`) without a link: it keeps the controller's state machine, integrates
motion lazily from the clock (no background task), refuses what the firmware would refuse,
pushes its changes to subscribers as the real controller does, and records every call so tests
can check that a bad request never reached it. The daemon reaches it only through a factory a
test passes in (tests/service/fake_daemon.py), never through anything in production code.
Tests of the link itself use the wire-level emulator in tests/link/fake_controller.py.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from host.control.api import PoseSample, PoseSink
from host.link.common import LinkState
from host.link.snapshot import ControllerChange, Listener, Snapshot
from protocol import PARAMS, Fault, Inputs, ParamId, State

DEFAULT_SPEED_MM_S = 100.0  # the paper's 0.1 m/s


class FakeControllerError(RuntimeError):
    """The fake refused a command the way the firmware would (a NAK)."""


class MemoryController:
    """Implements `host.control.api.ControllerLike` in memory."""

    def __init__(self, connect_delay_s: float = 0.0, fail_connect: bool = False) -> None:
        self.calls: list[tuple[str, tuple[object, ...]]] = []
        self.state = State.IDLE
        self.params = {spec.id: spec.default for spec in PARAMS}
        self.head_rad = (0.0, 0.0)
        self.homed = False
        self._connected = False
        self._connect_delay_s = connect_delay_s
        self._fail_connect = fail_connect
        self._from_mm = 0.0
        self._to_mm = 0.0
        self._speed_mm_s = 0.0
        self._t0 = time.monotonic()
        self._listeners: list[Listener] = []
        self._start_task: asyncio.Task[None] | None = None
        self.link_error = "not connected yet"

    @property
    def connected(self) -> bool:
        """True after connect, until close."""
        return self._connected

    def start(self) -> None:
        """Connect in the background, as the real controller does."""
        self._start_task = asyncio.get_running_loop().create_task(self._connect_pushed())

    async def _connect_pushed(self) -> None:
        """connect(), its outcome pushed as a link change."""
        try:
            await self.connect()
        except ConnectionError as exc:
            self.link_error = str(exc)
            self._push("link", LinkState.DOWN)
            return
        self._push("link")

    def subscribe(self, listener: Listener) -> Callable[[], None]:
        """Get pushed changes."""
        self._listeners.append(listener)
        return lambda: self._listeners.remove(listener)

    @property
    def position_mm(self) -> float:
        """Where the trolley is now on its current ramp-free profile."""
        travel = self._to_mm - self._from_mm
        done = self._speed_mm_s * (time.monotonic() - self._t0)
        if done >= abs(travel):
            if self.state is State.MOVING:
                self.state = State.READY
            return self._to_mm
        return self._from_mm + (done if travel > 0 else -done)

    async def connect(self) -> None:
        """Pretend to open the link (optionally slowly, or failing)."""
        self.calls.append(("connect", ()))
        if self._fail_connect:
            raise ConnectionError("fake controller: no device")
        if self._connect_delay_s:
            await asyncio.sleep(self._connect_delay_s)
        self._connected = True
        self.link_error = ""

    async def close(self) -> None:
        """Drop the link."""
        self.calls.append(("close", ()))
        if self._start_task is not None:
            self._start_task.cancel()
            await asyncio.gather(self._start_task, return_exceptions=True)
        self._connected = False

    async def home(self) -> None:
        """Homing completes at once in the fake."""
        self._command("home")
        self._require(State.IDLE, State.READY)
        self._go(0.0, 0.0, 1.0)
        self.state = State.READY
        self.homed = True
        self._push("state")

    async def move_to(self, mm: float, speed_mm_s: float | None = None) -> None:
        """Start an absolute move."""
        self._command("move_to", mm, speed_mm_s)
        self._require(State.READY, State.MOVING)
        self._go(self.position_mm, mm, speed_mm_s or DEFAULT_SPEED_MM_S)
        self.state = State.MOVING
        self._push("state")

    async def jog(self, mm_s: float) -> None:
        """Jog: modelled as a long move in the direction of travel."""
        self._command("jog", mm_s)
        self._require(State.IDLE, State.READY, State.MOVING)
        target = self.position_mm + (1e6 if mm_s > 0 else -1e6)
        self._go(self.position_mm, target, abs(mm_s))
        self.state = State.MOVING if mm_s else State.READY
        self._push("state")

    async def stop(self) -> None:
        """Stop where we are."""
        self._command("stop")
        here = self.position_mm
        self._go(here, here, 1.0)
        if self.state is State.MOVING:
            self.state = State.READY
        self._push("state")

    async def estop(self) -> None:
        """Latch the e-stop."""
        self._command("estop")
        here = self.position_mm
        self._go(here, here, 1.0)
        self.state = State.ESTOP
        self._push("state")

    async def clear_fault(self) -> None:
        """Release a latch back to IDLE."""
        self._command("clear_fault")
        if self.state in (State.ESTOP, State.FAULT):
            self.state = State.IDLE
        self._push("state")

    async def set_head(self, pan_rad: float, tilt_rad: float) -> None:
        """Point the head."""
        self._command("set_head", pan_rad, tilt_rad)
        self.head_rad = (pan_rad, tilt_rad)

    async def get_param(self, param_id: int) -> int:
        """Read a parameter."""
        self._command("get_param", param_id)
        return self.params[ParamId(param_id)]

    async def set_param(self, param_id: int, value: int) -> None:
        """Write a parameter."""
        self._command("set_param", param_id, value)
        self.params[ParamId(param_id)] = value

    async def persist_params(self) -> None:
        """Nothing to store in memory."""
        self._command("persist_params")

    def snapshot(self, link: LinkState | None = None) -> Snapshot:
        """State as the real controller's snapshot (typed, and plain as a mapping)."""
        now = time.monotonic_ns()
        link = link or (LinkState.UP if self._connected else LinkState.DISCONNECTED)
        inputs = int(Inputs.HOMED) if self.homed else 0
        track = "on" if self.homed else None
        return Snapshot(
            link, self.state, Fault.NONE, inputs, self.position_mm, now, now, self.homed, track,
            self.head_rad, self.link_error,
        )  # fmt: skip

    def link_stats(self) -> dict[str, object]:
        """Counters of the fake link."""
        return {"connected": self._connected, "commands": len(self.calls), "frames_lost": 0}

    def _push(self, topic: str, link: LinkState | None = None) -> None:
        """Hand a change to the subscribers, as the real controller does."""
        change = ControllerChange(topic, self.snapshot(link))
        for listener in list(self._listeners):
            listener(change)

    def _command(self, name: str, *args: object) -> None:
        """Record a call; refuse it when the link is down."""
        self.calls.append((name, args))
        if not self._connected:
            raise FakeControllerError("link is down")

    def _require(self, *states: State) -> None:
        """NAK BAD_STATE unless in one of `states`."""
        if self.state not in states:
            raise FakeControllerError(f"NAK BAD_STATE in {self.state.name}")

    def _go(self, from_mm: float, to_mm: float, speed_mm_s: float) -> None:
        """Start a constant-speed profile now."""
        self._from_mm, self._to_mm, self._speed_mm_s = from_mm, to_mm, speed_mm_s
        self._t0 = time.monotonic()


class MemoryFrameLoop:
    """Poses from the fake controller at a fixed rate: camera 4 m up looking along +Y."""

    def __init__(
        self,
        controller: MemoryController,
        sink: PoseSink,
        fps: float = 30.0,
        height_mm: float = 4000.0,
    ) -> None:
        self.controller = controller
        self.sink = sink
        self.period_s = 1.0 / fps
        self.height_mm = height_mm
        self.frames = 0
        self._fps = 0.0

    @property
    def fps(self) -> float:
        """The configured rate once frames flow."""
        return self._fps

    async def run(self) -> None:
        """Emit a pose per period until cancelled."""
        while True:
            await asyncio.sleep(self.period_s)
            x = self.controller.position_mm
            matrix = ((1.0, 0.0, 0.0, x), (0.0, 0.0, 1.0, 0.0), (0.0, -1.0, 0.0, self.height_mm))
            pose = PoseSample(
                time.monotonic_ns(),
                (*matrix, (0.0, 0.0, 0.0, 1.0)),
                self.controller.state.name,
                x,
                homed=self.controller.homed,
            )
            self.frames += 1
            self._fps = 1.0 / self.period_s
            self.sink(pose)
