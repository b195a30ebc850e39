"""The small interfaces the service layer is built against, so the real objects plug in later.

`ControllerLike` is the part of `host.link.Controller` the daemon and the control socket call;
`FrameLoopLike` is the frame loop (camera → pose → overlay) seen from the daemon. Both are
structural Protocols: the lead wires the real classes (or a thin adapter) without inheritance.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from protocol import ParamId

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
    """The controller API the service calls (host.link.Controller provides it)."""

    @property
    def connected(self) -> bool:
        """True while the session with the controller is up."""
        ...

    async def connect(self) -> None:
        """Open the link and handshake; raises when the controller is not reachable."""

    async def close(self) -> None:
        """Close the link."""

    async def home(self) -> None:
        """Start homing."""

    async def move_to(self, position_mm: float, speed_mm_s: float | None = None) -> None:
        """Absolute move along the track."""

    async def jog(self, velocity_mm_s: float) -> None:
        """Constant-velocity motion; 0 stops."""

    async def stop(self) -> None:
        """Controlled stop (the command is acknowledged when the ramp starts)."""

    async def estop(self) -> None:
        """Emergency stop, latched until clear_fault."""

    async def clear_fault(self) -> None:
        """Release a latched fault or e-stop."""

    async def set_head(self, pan_rad: float, tilt_rad: float) -> None:
        """Point the pan/tilt head."""

    async def get_param(self, param: ParamId) -> int:
        """Read a controller parameter."""
        ...

    async def set_param(self, param: ParamId, value: int) -> None:
        """Write a controller parameter (RAM only)."""

    async def persist_params(self) -> None:
        """Store the parameters in flash."""

    def snapshot(self) -> Mapping[str, Any]:
        """The latest controller state as plain values (state, faults, position_mm, …)."""
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
