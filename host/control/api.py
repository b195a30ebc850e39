"""What the service layer is typed against: poses, the controller's surface, the frame loop.

`host.link.Controller` is the one controller; the daemon, the control operations and the
outputs call it directly. `ControllerLike` is nothing but its public surface written down as a
structural type, so that test doubles (tests/fakes.py) are checked against the same methods;
there is no adapter between them. `FrameLoopLike` is the frame loop seen from the daemon.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from host.link.snapshot import Listener

Matrix4 = Sequence[Sequence[float]] | npt.NDArray[np.float64]


@dataclass(frozen=True)
class PoseSample:
    """The camera pose registered for one frame."""

    t_ns: int  # host monotonic time of the frame's exposure
    T_w_c: Matrix4  # camera in world, millimetres
    state: str  # controller state name when the pose was computed
    s_mm: float | None = None  # trolley arc length along the track, if known
    frame_index: int = 0
    homed: bool = False  # the controller's position was referenced to home (else: flagged)

    def to_dict(self) -> dict[str, Any]:
        """Plain types for msgpack events and recordings."""
        return {
            "t_ns": self.t_ns,
            "T_w_c": [[float(x) for x in row] for row in self.T_w_c],
            "state": self.state,
            "s_mm": self.s_mm,
            "frame_index": self.frame_index,
            "homed": self.homed,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> PoseSample:
        """Inverse of `to_dict`."""
        matrix = tuple(tuple(float(x) for x in row) for row in data["T_w_c"])
        s_mm = data.get("s_mm")
        return cls(
            int(data["t_ns"]),
            matrix,
            str(data["state"]),
            None if s_mm is None else float(s_mm),
            int(data.get("frame_index", 0)),
            bool(data.get("homed", False)),
        )


@runtime_checkable
class ControllerLike(Protocol):
    """The public surface of `host.link.Controller` (its only production implementation)."""

    @property
    def connected(self) -> bool:
        """True while the session with the controller is up."""
        ...

    @property
    def link_error(self) -> str:
        """Why the link is not up (empty while it is)."""
        ...

    def start(self) -> None:
        """Connect in the background and keep the link up; never raises."""

    def subscribe(self, listener: Listener) -> Callable[[], None]:
        """Push every link and controller-state change to `listener`; returns the unsubscriber."""
        ...

    async def close(self) -> None:
        """Close the link."""

    async def home(self) -> object:
        """Start homing (at the controller's HOME_SPEED)."""

    async def move_to(self, mm: float, speed_mm_s: float | None = None) -> object:
        """Absolute move along the track (the default speed when None)."""

    async def jog(self, mm_s: float) -> object:
        """Constant-velocity motion; 0 stops."""

    async def stop(self) -> None:
        """Controlled stop (the command is acknowledged when the ramp starts)."""

    async def estop(self) -> None:
        """Emergency stop, latched until clear_fault."""

    async def clear_fault(self) -> None:
        """Release a latched fault or e-stop."""

    async def set_head(self, pan_rad: float, tilt_rad: float) -> None:
        """Point the pan/tilt head."""

    async def get_param(self, param_id: int) -> int:
        """Read a controller parameter."""
        ...

    async def set_param(self, param_id: int, value: int) -> object:
        """Write a controller parameter (RAM only)."""

    async def persist_params(self) -> None:
        """Store the parameters in flash."""

    def snapshot(self) -> Mapping[str, Any]:
        """The latest controller state as plain values (state, faults, position_mm, age_s, …)."""
        ...

    def link_stats(self) -> Mapping[str, Any]:
        """Link counters as plain values (frames, retransmits, losses, rtt, …)."""
        ...


PoseSink = Callable[[PoseSample], None]


@runtime_checkable
class FrameLoopLike(Protocol):
    """The frame loop as the daemon sees it: run until cancelled, report every pose."""

    @property
    def fps(self) -> float:
        """Frames registered per second, recently."""
        ...

    async def run(self) -> None:
        """Register frames until cancelled, calling the pose sink for each."""
