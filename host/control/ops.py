"""The control operations: argument checks and calls into the controller (docs/CONTROL.md).

Each op is a row of `OPS`: its handler and whether it needs the operator role. Handlers check
their arguments before anything reaches the controller, so a bad request never moves the
trolley; a controller failure becomes a `failed` error carrying the controller's message.
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any

from host.control.api import ControllerLike, PoseSample
from protocol import PARAMS_BY_ID, ParamId

MAX_SPEED_MM_S = 2000.0  # the wire's MAX_SPEED ceiling, 2 m/s
MAX_POSITION_MM = 1e6


class OpError(Exception):
    """A request that cannot be served; `code` goes into the error reply."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass
class OpContext:
    """What the ops can see: the controller and the daemon's read-only providers."""

    controller: ControllerLike | None
    latest_pose: Callable[[], PoseSample | None] = lambda: None
    service_status: Callable[[], Mapping[str, Any]] = dict
    calibration: Callable[[], Mapping[str, Any]] = dict
    pan_limits_rad: tuple[float, float] = (-math.pi, math.pi)
    tilt_limits_rad: tuple[float, float] = (-math.pi / 2, math.pi / 2)
    commissioning: Any = None  # host.commissioning.env.CommissioningEnv (docs/COMMISSIONING.md)


Handler = Callable[[OpContext, Mapping[str, Any]], Awaitable[Any]]


def number(args: Mapping[str, Any], key: str, lo: float, hi: float) -> float:
    """A finite number argument within [lo, hi]."""
    if key not in args:
        raise OpError("bad_args", f"missing argument {key!r}")
    value = args[key]
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise OpError("bad_args", f"{key} = {value!r}: expected a finite number")
    if not lo <= value <= hi:
        raise OpError("out_of_range", f"{key} = {value!r}: outside [{lo}, {hi}]")
    return float(value)


def param_id(args: Mapping[str, Any]) -> ParamId:
    """The `param` argument, by name (MAX_SPEED_UM_S) or by wire id."""
    value = args.get("param")
    try:
        if isinstance(value, str):
            return ParamId[value.upper()]
        if isinstance(value, int) and not isinstance(value, bool):
            return ParamId(value)
    except (KeyError, ValueError):
        pass
    raise OpError("bad_args", f"param = {value!r}: not a parameter name or id")


def _controller(ctx: OpContext) -> ControllerLike:
    """The controller, or `unavailable` while the link is down."""
    if ctx.controller is None or not ctx.controller.connected:
        raise OpError("unavailable", "the controller link is not up")
    return ctx.controller


async def op_status(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Service, controller and pose in one map."""
    pose = ctx.latest_pose()
    state = dict(ctx.controller.snapshot()) if ctx.controller is not None else {}
    connected = ctx.controller is not None and ctx.controller.connected
    return {
        "service": dict(ctx.service_status()),
        "link_up": connected,
        "controller": state,
        "pose": None if pose is None else pose.to_dict(),
    }


async def op_link_stats(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """The controller link's counters."""
    if ctx.controller is None:
        raise OpError("unavailable", "no controller configured")
    return dict(ctx.controller.link_stats())


async def op_calibration(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """The calibration in use (intrinsics, M_cr, source)."""
    return dict(ctx.calibration())


async def op_home(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Start homing."""
    await _controller(ctx).home()
    return None


async def op_move(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Absolute move: position_mm, optional speed_mm_s."""
    position = number(args, "position_mm", -MAX_POSITION_MM, MAX_POSITION_MM)
    speed = None
    if args.get("speed_mm_s") is not None:
        speed = number(args, "speed_mm_s", 1e-3, MAX_SPEED_MM_S)
    await _controller(ctx).move_to(position, speed)
    return None


async def op_jog(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Constant velocity: velocity_mm_s (0 stops)."""
    velocity = number(args, "velocity_mm_s", -MAX_SPEED_MM_S, MAX_SPEED_MM_S)
    await _controller(ctx).jog(velocity)
    return None


async def op_stop(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Controlled stop."""
    cancel_runs(ctx, "STOP")  # first, so a calibration run cannot command a motion after it
    await _controller(ctx).stop()
    return None


async def op_estop(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Emergency stop."""
    cancel_runs(ctx, "ESTOP")
    await _controller(ctx).estop()
    return None


async def op_clear(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Clear a latched fault or e-stop."""
    await _controller(ctx).clear_fault()
    return None


async def op_head(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Point the head: pan_rad, tilt_rad within the configured limits."""
    pan = number(args, "pan_rad", *ctx.pan_limits_rad)
    tilt = number(args, "tilt_rad", *ctx.tilt_limits_rad)
    await _controller(ctx).set_head(pan, tilt)
    return None


async def op_param_get(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Read one parameter."""
    pid = param_id(args)
    value = await _controller(ctx).get_param(pid)
    return {"param": pid.name, "value": int(value), "unit": PARAMS_BY_ID[pid].unit}


async def op_param_set(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Write one parameter after checking it against the parameter table."""
    pid = param_id(args)
    spec = PARAMS_BY_ID[pid]
    value = args.get("value")
    if isinstance(value, bool) or not isinstance(value, int):
        raise OpError("bad_args", f"value = {value!r}: expected an integer")
    if not spec.lo <= value <= spec.hi:
        raise OpError("out_of_range", f"{pid.name} = {value}: outside [{spec.lo}, {spec.hi}]")
    await _controller(ctx).set_param(pid, value)
    return {"param": pid.name, "value": value}


async def op_param_persist(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Store the parameters in flash."""
    await _controller(ctx).persist_params()
    return None


# op name → (handler, needs the operator role)
OPS: dict[str, tuple[Handler, bool]] = {
    "status": (op_status, False),
    "link_stats": (op_link_stats, False),
    "calibration": (op_calibration, False),
    "param_get": (op_param_get, False),
    "home": (op_home, True),
    "move": (op_move, True),
    "jog": (op_jog, True),
    "stop": (op_stop, True),
    "estop": (op_estop, True),
    "clear": (op_clear, True),
    "head": (op_head, True),
    "param_set": (op_param_set, True),
    "param_persist": (op_param_persist, True),
}

# The commissioning runs (calibrate_*, survey_*): their own module, joined to the table here.
from host.commissioning.ops import COMMISSIONING_OPS, cancel_runs  # noqa: E402

OPS.update(COMMISSIONING_OPS)
