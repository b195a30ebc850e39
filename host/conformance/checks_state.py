"""Checks of the state machine: the acceptance table cell by cell, STATUS, faults, homing."""

from __future__ import annotations

from collections.abc import Awaitable, Callable

from host.conformance.base import (
    ACCEL_UM_S2,
    JOG_UM_S,
    SHORT_WATCHDOG_MS,
    SLOW_HOME_UM_S,
    STOP_TIMEOUT_S,
    Context,
    check,
    expect,
    expect_ack,
    expect_nak,
)
from host.conformance.wire import Received
from protocol import Fault, Inputs, NakCode, ParamId, State, Stream
from protocol.messages import (
    Ack,
    ClearFault,
    EncoderSample,
    Estop,
    HeadSet,
    Home,
    Jog,
    MoveTo,
    ParamGet,
    ParamPersist,
    ParamSet,
    Status,
    Stop,
    StreamSet,
)

OK = None  # an accepted cell
BS, NH = NakCode.BAD_STATE, NakCode.NOT_HOMED
MOVE_UM = 40_000
MOVING_CPS = 300  # encoder counts/s that are motion, not a settling trolley
SETTLE_S = 3.0
MOVE_SPEED_UM_S = 100_000
# PROTOCOL.md §10, the cells a probe can test without leaving the state (no-ops and refusals).
# The accepted cells that change the state are checked by the flows further down.
TABLE: dict[str, dict[State, NakCode | None]] = {
    "HOME": {State.HOMING: BS, State.MOVING: BS, State.FAULT: BS, State.ESTOP: BS},
    "MOVE_TO": {State.IDLE: NH, State.HOMING: BS, State.FAULT: BS, State.ESTOP: BS},
    "JOG": {State.HOMING: BS, State.FAULT: BS, State.ESTOP: BS},
    "HEAD_SET": dict.fromkeys((State.IDLE, State.HOMING, State.READY, State.MOVING), OK)
    | {State.FAULT: BS, State.ESTOP: BS},
    "PARAM_SET": {State.IDLE: OK, State.HOMING: BS, State.READY: OK, State.MOVING: BS}
    | {State.FAULT: OK, State.ESTOP: OK},
    "PARAM_PERSIST": {State.IDLE: OK, State.HOMING: BS, State.READY: OK, State.MOVING: BS}
    | {State.FAULT: OK, State.ESTOP: OK},
    "PARAM_GET": dict.fromkeys(State, OK),
    "STREAM_SET": dict.fromkeys(State, OK),
    "CLEAR_FAULT": dict.fromkeys((State.IDLE, State.HOMING, State.READY, State.MOVING), OK),
    "STOP": {State.IDLE: OK, State.READY: OK, State.FAULT: OK, State.ESTOP: OK},
}


def _probe(name: str) -> object:
    """The command a table row sends."""
    return {
        "HOME": Home(0),
        "MOVE_TO": MoveTo(MOVE_UM, MOVE_SPEED_UM_S, ACCEL_UM_S2),
        "JOG": Jog(JOG_UM_S, ACCEL_UM_S2),
        "HEAD_SET": HeadSet(0, 0),
        "PARAM_SET": ParamSet(int(ParamId.HOME_OFFSET_UM), 0),
        "PARAM_PERSIST": ParamPersist(),
        "PARAM_GET": ParamGet(int(ParamId.WATCHDOG_MS)),
        "STREAM_SET": StreamSet(int(Stream.RANGE), 0),
        "CLEAR_FAULT": ClearFault(),
        "STOP": Stop(),
    }[name]


async def _probe_state(ctx: Context, state: State) -> None:
    """Send every row's probe in `state` and compare with the table."""
    for name, row in TABLE.items():
        if state not in row:
            continue
        reply = await ctx.client.request(_probe(name))
        code = row[state]
        if code is None:
            expect(not hasattr(reply, "code"), f"{name} in {state.name}: expected ✓, got {reply!r}")
            expect(
                getattr(reply, "state", state) == state,
                f"{name} in {state.name} left the state: {reply!r}",
            )
        else:
            expect_nak(reply, code, state, f"{name} in {state.name}")


@check("state table: every no-op and refusal, state by state", "R-STATE-1", motion=True)
async def state_table(ctx: Context) -> None:
    entries: list[tuple[State, Callable[[], Awaitable[None]]]] = [
        (State.IDLE, ctx.fresh),
        (State.ESTOP, ctx.to_estop),
        (State.FAULT, ctx.to_fault),
        (State.READY, ctx.to_ready),
        (State.MOVING, lambda: ctx.to_moving(homed=True)),
        (State.HOMING, ctx.to_homing),
    ]
    for state, enter in entries:
        await enter()
        await _probe_state(ctx, state)
        if state in (State.MOVING, State.HOMING):
            await ctx.stop_and_settle()


@check("state table: the cells that change the state", "R-STATE-1", "R-STATE-2", motion=True)
async def state_flows(ctx: Context) -> None:
    c = ctx.client
    await ctx.fresh()
    mark = c.mark()
    expect_ack(await c.request(Jog(JOG_UM_S, ACCEL_UM_S2)), "JOG in IDLE")
    await c.wait_status(lambda s: s.state == State.MOVING, 1.0, mark, "STATUS MOVING")
    await ctx.stop_and_settle()
    await c.wait_status(lambda s: s.state == State.IDLE, 1.0, mark, "STATUS IDLE after STOP")
    await ctx.to_homing()
    mark = c.mark()
    reply = expect_ack(await c.request(Stop()), "STOP in HOMING")
    expect(reply.state in (State.MOVING, State.IDLE), f"STOP in HOMING acked {reply!r}")
    await c.wait_status(lambda s: s.state == State.IDLE, STOP_TIMEOUT_S, mark, "IDLE")
    await ctx.home()  # HOME in IDLE → HOMING → READY
    mark = c.mark()
    seq = c.seq
    expect_ack(await c.request(MoveTo(MOVE_UM, MOVE_SPEED_UM_S, ACCEL_UM_S2)), "MOVE_TO")
    done = await c.wait_status(lambda s: s.state == State.READY, 10.0, mark, "motion complete")
    expect(done.cmd_seq == seq, f"READY after MOVE_TO should carry its seq {seq}: {done!r}")
    expect_ack(await c.request(Jog(JOG_UM_S, ACCEL_UM_S2)), "JOG in READY")
    expect_ack(await c.request(MoveTo(0, MOVE_SPEED_UM_S, ACCEL_UM_S2)), "MOVE_TO replaces")
    expect_ack(await c.request(Jog(JOG_UM_S // 2, ACCEL_UM_S2)), "JOG replaces")
    await ctx.stop_and_settle()
    reply = expect_ack(await c.request(Home(ctx.options.home_speed_um_s)), "HOME in READY")
    expect(reply.state == State.HOMING, f"HOME in READY acked {reply!r}")
    mark = c.mark()
    expect_ack(await c.request(Estop()), "ESTOP in HOMING")
    status = await c.wait_status(lambda s: s.state == State.ESTOP, 1.0, mark, "STATUS ESTOP")
    expect(bool(status.faults & Fault.ESTOP), f"ESTOP fault bit: {status!r}")


@check("CLEAR_FAULT lands in IDLE, unhomed", "R-STATE-3", motion=True)
async def clear_fault(ctx: Context) -> None:
    c = ctx.client
    await ctx.to_ready()
    expect_ack(await c.request(Estop()), "ESTOP")
    mark = c.mark()
    reply = expect_ack(await c.request(ClearFault()), "CLEAR_FAULT after ESTOP")
    expect(reply.state == State.IDLE, f"CLEAR_FAULT after ESTOP acked {reply!r}")
    status = await c.wait_status(lambda s: s.state == State.IDLE, 1.0, mark, "STATUS IDLE")
    expect(not status.inputs & Inputs.HOMED, f"still HOMED after CLEAR_FAULT: {status!r}")
    expect_nak(await c.request(MoveTo(MOVE_UM, 1000, 1000)), NakCode.NOT_HOMED, State.IDLE)
    await ctx.to_fault()
    reply = expect_ack(await c.request(ClearFault()), "CLEAR_FAULT after WATCHDOG")
    expect(reply.state == State.IDLE, f"CLEAR_FAULT after WATCHDOG acked {reply!r}")


@check("the watchdog faults IDLE, READY, HOMING and MOVING", "R-WD-1", motion=True)
async def watchdog(ctx: Context) -> None:
    c = ctx.client
    for state in (State.IDLE, State.READY, State.HOMING, State.MOVING):
        await ctx.fresh()
        if state is not State.IDLE:
            await ctx.home()
        await ctx.set_param(ParamId.WATCHDOG_MS, SHORT_WATCHDOG_MS)  # only at standstill
        if state is State.HOMING:
            expect_ack(await c.request(Home(SLOW_HOME_UM_S)), "HOME")
        elif state is State.MOVING:
            expect_ack(await c.request(Jog(JOG_UM_S, ACCEL_UM_S2)), "JOG")
        status = await ctx.silence_until_fault()
        expect(status.state == State.FAULT, f"watchdog from {state.name}: {status!r}")


@check("homing latches the index; homing again backs off past the switch", "R-HOME-1",
       "R-HOME-2", motion=True)  # fmt: skip
async def homing(ctx: Context) -> None:
    c = ctx.client
    await ctx.to_ready()
    offset = await ctx.param(ParamId.HOME_OFFSET_UM)
    first = await _status_now(ctx)
    expect(abs(first.target_um - offset) < 100, f"homed to {first.target_um} µm, not {offset}")
    # Homed, the trolley sits on the index, behind the switch: HOME again must back off first.
    expect_ack(await c.request(StreamSet(int(Stream.ENCODER), 200)), "STREAM_SET")
    # READY means the commanded profile ended; let the trolley itself come to rest.
    await c.wait_for(_at_rest, SETTLE_S, c.mark(), raise_on_timeout=False)
    mark = c.mark()
    await ctx.home()
    await c.request(StreamSet(int(Stream.ENCODER), 0))
    acked = next(i for i, r in enumerate(c.received) if i >= mark and isinstance(r.message, Ack))
    moving = [s for s in c.since(acked, EncoderSample) if abs(s.velocity_counts_s) > MOVING_CPS]
    expect(bool(moving), "no motion seen while homing again")
    expect(moving[0].velocity_counts_s > 0, "homing again from behind the switch went negative")
    second = await _status_now(ctx)
    expect(abs(second.target_um - offset) < 100, f"homed again to {second.target_um} µm")


def _at_rest(r: Received) -> bool:
    """An ENCODER_SAMPLE of a trolley standing still."""
    msg = r.message
    return isinstance(msg, EncoderSample) and abs(msg.velocity_counts_s) < MOVING_CPS // 3


async def _status_now(ctx: Context) -> Status:
    """One STATUS sample from the stream."""
    c = ctx.client
    mark = c.mark()
    await c.request(StreamSet(int(Stream.STATUS), 50))
    status = await c.wait_status(lambda s: True, 1.0, mark, "a STATUS sample")
    await c.request(StreamSet(int(Stream.STATUS), 0))
    return status


@check("speeds above the ceiling are limited, targets rounded to microsteps", "R-CLAMP-1",
       motion=True)  # fmt: skip
async def clamping(ctx: Context) -> None:
    c = ctx.client
    await ctx.to_ready()
    ident = c.identity
    assert ident is not None
    um_per_rev = ident.sprocket_teeth * ident.chain_pitch_um
    target = MOVE_UM + 13
    steps = _round(target * ident.steps_per_rev, um_per_rev)
    expected = _round(steps * um_per_rev, ident.steps_per_rev)
    mark = c.mark()
    reply = await c.request(MoveTo(target, 2_000_000, 10_000_000))
    expect_ack(reply, "MOVE_TO above MAX_SPEED/MAX_ACCEL is accepted, not refused")
    status = await c.wait_status(lambda s: s.state == State.MOVING, 1.0, mark, "MOVING")
    expect(status.target_um == expected, f"target {status.target_um} µm, expected {expected}")
    await c.wait_status(lambda s: s.state == State.READY, 10.0, mark, "READY")


def _round(num: int, den: int) -> int:
    """Nearest integer, halves away from zero."""
    q = (abs(num) + den // 2) // den
    return q if num >= 0 else -q
