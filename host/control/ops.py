"""The control operations: argument checks, role checks and calls into the controller.

Each op is a row of `OPS`: its handler and the least role that may run it. `dispatch` is the one
way in for every caller (the control socket, the CLI through it, the operator station): it takes
a role, an op name and its arguments and returns a reply body, never raising for a bad request
or a controller failure. Handlers check their arguments before anything reaches the controller,
so a bad request never moves the trolley. STOP and ESTOP run for any authenticated role and say
in their reply what happened, including, while the link is down, that the controller's own
watchdog is what stops the trolley (docs/CONTROL.md).
"""

from __future__ import annotations

import contextlib
import enum
import math
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import Any

from host.control.api import ControllerLike, PoseSample
from host.link.common import CommandTimeout, LinkDown
from protocol import PARAMS_BY_ID, ParamId

MAX_SPEED_MM_S = 2000.0  # the wire's MAX_SPEED ceiling, 2 m/s
MAX_POSITION_MM = 1e6


SAFETY_OPS = frozenset({"stop", "estop"})  # any role, past every per-client limit
MOTION_OPS = frozenset({"home", "move", "jog", "head", "clear"})
LOST_REPLY_TEXT = (
    "; the command may have reached the controller and be running (its reply was lost): "
    "check `orbitar status` before repeating it, stop the trolley if it moves"
)
WATCHDOG_DEFAULT_MS = PARAMS_BY_ID[ParamId.WATCHDOG_MS].default


class Role(enum.Enum):
    """What a client may do; a higher role may do everything a lower one may."""

    NONE = "none"  # TCP client before a successful hello
    VIEWER = "viewer"  # read-only ops, subscriptions, stop and estop
    OPERATOR = "operator"  # everything, motion included

    def allows(self, least: Role) -> bool:
        """True if this role may run what needs `least`."""
        return _RANK[self] >= _RANK[least]


_RANK = {Role.NONE: 0, Role.VIEWER: 1, Role.OPERATOR: 2}


class OpError(Exception):
    """A request that cannot be served; `code` and `detail` go into the error reply."""

    def __init__(self, code: str, message: str, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.detail = detail

    def reply(self) -> dict[str, Any]:
        """The error as a reply body."""
        error: dict[str, Any] = {"code": self.code, "message": str(self)}
        if self.detail:
            error["detail"] = self.detail
        return {"ok": False, "error": error}


@dataclass
class OpContext:
    """What the ops can see: the controller and the daemon's read-only providers."""

    controller: ControllerLike | None
    latest_pose: Callable[[], PoseSample | None] = lambda: None
    service_status: Callable[[], Mapping[str, Any]] = dict
    calibration: Callable[[], Mapping[str, Any]] = dict
    pan_limits_rad: tuple[float, float] = (-math.pi, math.pi)
    tilt_limits_rad: tuple[float, float] = (-math.pi / 2, math.pi / 2)
    watchdog_ms: int | None = None  # the controller's WATCHDOG_MS, once read or written here
    control_stats: Callable[[], Mapping[str, Any]] = dict  # the control server's counters
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
    if ctx.controller is None:
        raise OpError("unavailable", "the controller link is not up")
    if not ctx.controller.connected:
        cause = ctx.controller.link_error
        raise OpError("unavailable", f"the controller link is not up: {cause or 'closed'}")
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
        "control": dict(ctx.control_stats()),
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
    """Controlled stop; the reply says whether the controller acknowledged it."""
    return await _safety(ctx, "stop")


async def op_estop(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Emergency stop; the reply says whether the controller acknowledged it."""
    return await _safety(ctx, "estop")


async def _safety(ctx: OpContext, op: str) -> dict[str, Any]:
    """Send stop/estop, or explain who stops the trolley when it cannot be sent."""
    cancel_runs(ctx, op.upper())  # first, so a calibration run cannot command a motion after it
    controller = ctx.controller
    watchdog_ms, known = _watchdog_ms(ctx)
    detail: dict[str, Any] = {"sent": False, "acked": False, "watchdog_ms": watchdog_ms}
    detail["watchdog_known"] = known
    period = f"{watchdog_ms} ms" if known else f"{watchdog_ms} ms, the default, unless changed"
    if controller is None or not controller.connected:
        why = "no controller is configured" if controller is None else "the controller link is down"
        raise OpError(
            "unavailable",
            f"{op} not sent: {why}; the controller's own watchdog stops the trolley "
            f"(controlled stop, WATCHDOG fault) within WATCHDOG_MS ({period}) of the last frame "
            "it received from the host; use the hardware e-stop if it still moves",
            detail,
        )
    try:
        await (controller.estop() if op == "estop" else controller.stop())
    except Exception as exc:  # a NAK or a lost ACK: say so, with what the operator can do
        detail["sent"] = True
        raise OpError(
            "failed",
            f"{op} sent but not acknowledged: {type(exc).__name__}: {exc}; "
            "repeat it, or use the hardware e-stop",
            detail,
        ) from exc
    return {"sent": True, "acked": True}


def _watchdog_ms(ctx: OpContext) -> tuple[int, bool]:
    """The controller's watchdog period and whether it is known (else the protocol default)."""
    if ctx.watchdog_ms is not None:
        return ctx.watchdog_ms, True
    if ctx.controller is not None:
        with contextlib.suppress(Exception):  # a snapshot must never hide the stop's answer
            value = ctx.controller.snapshot().get("watchdog_ms")
            if isinstance(value, int) and not isinstance(value, bool) and value > 0:
                return value, True
    return WATCHDOG_DEFAULT_MS, False


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
    if pid is ParamId.WATCHDOG_MS:
        ctx.watchdog_ms = int(value)
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
    if pid is ParamId.WATCHDOG_MS:
        ctx.watchdog_ms = value
    return {"param": pid.name, "value": value}


async def op_param_persist(ctx: OpContext, args: Mapping[str, Any]) -> Any:
    """Store the parameters in flash."""
    await _controller(ctx).persist_params()
    return None


# op name → (handler, the least role that may run it)
OPS: dict[str, tuple[Handler, Role]] = {
    "status": (op_status, Role.VIEWER),
    "link_stats": (op_link_stats, Role.VIEWER),
    "calibration": (op_calibration, Role.VIEWER),
    "param_get": (op_param_get, Role.VIEWER),
    "stop": (op_stop, Role.VIEWER),
    "estop": (op_estop, Role.VIEWER),
    "home": (op_home, Role.OPERATOR),
    "move": (op_move, Role.OPERATOR),
    "jog": (op_jog, Role.OPERATOR),
    "clear": (op_clear, Role.OPERATOR),
    "head": (op_head, Role.OPERATOR),
    "param_set": (op_param_set, Role.OPERATOR),
    "param_persist": (op_param_persist, Role.OPERATOR),
}


async def dispatch(ctx: OpContext, role: Role, op: Any, args: Any) -> dict[str, Any]:
    """Run one op for a caller of `role`: {"ok": true, "result"} or {"ok": false, "error"}."""
    try:
        return {"ok": True, "result": await _run(ctx, role, op, args)}
    except OpError as exc:
        return exc.reply()
    except (CommandTimeout, LinkDown) as exc:
        if op not in MOTION_OPS:
            return OpError("failed", f"{type(exc).__name__}: {exc}").reply()
        # The frame went out and no reply came back: the trolley may be moving as asked.
        detail = {"acked": False, "may_have_run": True}
        text = f"{type(exc).__name__}: {exc}{LOST_REPLY_TEXT}"
        return OpError("failed", text, detail).reply()
    except Exception as exc:  # a controller failure must not reach the caller as an exception
        return OpError("failed", f"{type(exc).__name__}: {exc}").reply()


async def _run(ctx: OpContext, role: Role, op: Any, args: Any) -> Any:
    """Check the request and the role, then call the handler."""
    if not isinstance(op, str) or not isinstance(args, Mapping):
        raise OpError("bad_request", 'a request needs a string "op" and a map "args"')
    if role is Role.NONE:
        raise OpError("unauthorized", 'send "hello" with a token first')
    if op not in OPS:
        raise OpError("unknown_op", f"unknown op {op!r}")
    handler, least = OPS[op]
    if not role.allows(least):
        raise OpError("forbidden", f"{op!r} needs the {least.value} role")
    return await handler(ctx, args)


# The commissioning runs (calibrate_*, survey_*): their own module, joined to the table here.
from host.commissioning.ops import COMMISSIONING_OPS, cancel_runs  # noqa: E402

OPS.update(COMMISSIONING_OPS)
