"""The suite's registry and the context every check runs in: how to reach each state by wire.

A check is an async function of a `Context`, registered with the PROTOCOL.md rule ids it covers.
Checks that move the trolley are marked `motion`; `--no-motion` skips them (reported as
skipped, never as passed). Every check starts from a fresh session on a freshly reset
controller, so checks do not depend on each other's leftovers.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from host.conformance.wire import ConformanceError, Received, WireClient
from protocol import SCHEMA, Fault, Inputs, NakCode, ParamId, State, Stream, cobs
from protocol.crc import frame_crc
from protocol.messages import (
    Ack,
    ClearFault,
    EncoderSample,
    Estop,
    Home,
    Jog,
    Nak,
    ParamGet,
    ParamSet,
    ParamValue,
    Reset,
    Status,
    Stop,
    StreamSet,
)
from protocol.schema import HEADER_FORMAT

CheckFn = Callable[["Context"], Awaitable[None]]
RESET_SETTLE_S = 0.3
HOMING_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 10.0
SHORT_WATCHDOG_MS = 100
JOG_UM_S = 20_000
RECOVER_UM_S = 100_000
RECOVER_TIMEOUT_S = 20.0
SLOW_HOME_UM_S = 5_000  # HOMING long enough to probe it, wherever the trolley starts
ACCEL_UM_S2 = 200_000


@dataclass(frozen=True)
class Check:
    """One registered check."""

    name: str
    rules: tuple[str, ...]
    fn: CheckFn
    motion: bool


CHECKS: list[Check] = []


def check(name: str, *rules: str, motion: bool = False) -> Callable[[CheckFn], CheckFn]:
    """Register a check covering PROTOCOL.md rule ids."""

    def wrap(fn: CheckFn) -> CheckFn:
        CHECKS.append(Check(name, rules, fn, motion))
        return fn

    return wrap


def expect(condition: bool, what: str) -> None:
    """ConformanceError with `what` unless the condition holds."""
    if not condition:
        raise ConformanceError(what)


def expect_nak(reply: object, code: NakCode, state: State | None = None, what: str = "") -> None:
    """The reply is a NAK with this code (and state)."""
    label = f"{what}: " if what else ""
    expect(isinstance(reply, Nak), f"{label}expected NAK {code.name}, got {reply!r}")
    assert isinstance(reply, Nak)
    expect(reply.code == code, f"{label}expected NAK {code.name}, got code {reply.code}")
    if state is not None:
        expect(reply.state == state, f"{label}NAK should carry state {state.name}: {reply!r}")


def expect_ack(reply: object, what: str = "") -> Ack:
    """The reply is an ACK."""
    label = f"{what}: " if what else ""
    expect(isinstance(reply, Ack), f"{label}expected ACK, got {reply!r}")
    assert isinstance(reply, Ack)
    return reply


def raw_wire(msg_id: int, payload: bytes, seq: int, flags: int = 1, version: int = 2) -> bytes:
    """A well-framed frame with any id and payload (beyond what the encoder allows)."""
    raw = struct.pack(HEADER_FORMAT, version, flags, seq, msg_id) + payload
    return cobs.encode(raw + frame_crc(raw).to_bytes(2, "big")) + b"\x00"


def raw_command(msg: object, seq: int, flags: int = 1) -> bytes:
    """A command encoded field by field without range checks (out-of-range tests)."""
    spec = SCHEMA.by_cls[type(msg)]
    values = [getattr(msg, f.name) for f in spec.fields]
    return raw_wire(spec.id, struct.pack(spec.struct_format, *values), seq, flags)


@dataclass
class Options:
    """What the operator allows and how fast homing may go."""

    motion: bool = True
    home_speed_um_s: int = 0  # 0: the controller's HOME_SPEED_UM_S


@dataclass
class Context:
    """A connected client and the ways to put the controller into each state."""

    client: WireClient
    options: Options = field(default_factory=Options)
    params: dict[int, int] = field(default_factory=dict)

    async def fresh(self) -> None:
        """RESET, then a new session: IDLE, unhomed, streams off, default parameters."""
        c = self.client
        await c.request(Reset())
        await asyncio.sleep(RESET_SETTLE_S)
        c.seq = (c.seq + 17) % (1 << 16)  # a new sequence: nothing of the old one is valid
        await c.hello()

    async def param(self, pid: ParamId) -> int:
        """A parameter's value in force."""
        reply = await self.client.request(ParamGet(int(pid)))
        expect(isinstance(reply, ParamValue), f"PARAM_GET {pid.name}: {reply!r}")
        return int(reply.value)

    async def set_param(self, pid: ParamId, value: int) -> None:
        """Set a parameter; ConformanceError if refused."""
        reply = await self.client.request(ParamSet(int(pid), value))
        expect(isinstance(reply, ParamValue), f"PARAM_SET {pid.name}={value}: {reply!r}")

    async def home(self) -> None:
        """HOME and wait for READY with HOMED; first back onto the track if behind the switch.

        The suite's own motions can leave the trolley between LIMIT_MIN and the home switch,
        where a conforming controller refuses HOME (BEYOND_LIMIT) or faults HARD_LIMIT.
        """
        for attempt in range(2):
            status = await self._home_once()
            if status.state == State.READY:
                expect(bool(status.inputs & Inputs.HOMED), f"READY without HOMED: {status!r}")
                return
            expect(attempt == 0 and bool(status.faults & Fault.HARD_LIMIT), f"homing: {status!r}")
            await self.back_past_the_switch()
        raise ConformanceError("homing failed twice")

    async def _home_once(self) -> Status:
        """One HOME: the STATUS it ends in (a BEYOND_LIMIT refusal reads as HARD_LIMIT)."""
        c = self.client
        mark = c.mark()
        reply = await c.request(Home(self.options.home_speed_um_s))
        if isinstance(reply, Nak) and reply.code == NakCode.BEYOND_LIMIT:
            return Status(0, reply.state, int(Fault.HARD_LIMIT), int(Inputs.LIMIT_MIN), 0, 0)
        expect_ack(reply, "HOME")
        return await c.wait_status(
            lambda s: s.state in (State.READY, State.FAULT, State.ESTOP),
            HOMING_TIMEOUT_S,
            mark,
            "homing",
        )

    async def back_past_the_switch(self) -> None:
        """Clear a fault, then jog positive over the home switch and stop beyond it."""
        c = self.client
        expect_ack(await c.request(ClearFault()), "CLEAR_FAULT")
        expect_ack(await c.request(StreamSet(int(Stream.ENCODER), 100)), "STREAM_SET")
        mark = c.mark()
        expect_ack(await c.request(Jog(RECOVER_UM_S, ACCEL_UM_S2)), "JOG back")
        seen = await c.wait_for(_on_switch(True), RECOVER_TIMEOUT_S, mark, raise_on_timeout=False)
        if seen is not None:
            await c.wait_for(_on_switch(False), RECOVER_TIMEOUT_S, c.received.index(seen))
        await self.stop_and_settle()
        await c.request(StreamSet(int(Stream.ENCODER), 0))

    async def to_ready(self) -> None:
        """Fresh controller, homed."""
        await self.fresh()
        await self.home()

    async def to_homing(self) -> None:
        """Fresh controller, homing just started."""
        await self.fresh()
        reply = await self.client.request(Home(SLOW_HOME_UM_S))
        expect(expect_ack(reply, "HOME").state == State.HOMING, f"HOME acked {reply!r}")

    async def to_moving(self, homed: bool) -> None:
        """Jogging slowly in the positive direction (from READY when `homed`)."""
        await (self.to_ready() if homed else self.fresh())
        reply = expect_ack(await self.client.request(Jog(JOG_UM_S, ACCEL_UM_S2)), "JOG")
        expect(reply.state == State.MOVING, f"JOG acked {reply!r}")

    async def to_fault(self) -> None:
        """A WATCHDOG fault from IDLE: a short watchdog and a silent host, then the watchdog
        back to its value (so a PARAM_PERSIST in FAULT stores nothing the suite changed)."""
        await self.fresh()
        watchdog_ms = await self.param(ParamId.WATCHDOG_MS)
        await self.set_param(ParamId.WATCHDOG_MS, SHORT_WATCHDOG_MS)
        await self.silence_until_fault()
        await self.set_param(ParamId.WATCHDOG_MS, watchdog_ms)

    async def silence_until_fault(self) -> Status:
        """Stop heartbeats until STATUS reports the WATCHDOG fault; heartbeats resume."""
        c = self.client
        mark = c.mark()
        c.heartbeats = False
        try:
            status = await c.wait_status(
                lambda s: bool(s.faults & Fault.WATCHDOG), 2.0, mark, "watchdog fault"
            )
        finally:
            c.heartbeats = True
        expect(status.state == State.FAULT, f"watchdog should enter FAULT: {status!r}")
        return status

    async def to_estop(self) -> None:
        """ESTOP latched from IDLE."""
        await self.fresh()
        expect_ack(await self.client.request(Estop()), "ESTOP")

    async def stop_and_settle(self) -> None:
        """STOP and wait until the controller stands still."""
        c = self.client
        mark = c.mark()
        reply = expect_ack(await c.request(Stop()), "STOP")
        if reply.state == State.MOVING:
            await c.wait_status(
                lambda s: s.state != State.MOVING, STOP_TIMEOUT_S, mark, "stop to finish"
            )


def _on_switch(closed: bool) -> Callable[[Received], bool]:
    """Accept an ENCODER_SAMPLE whose HOME input is (or is not) closed."""

    def accept(r: Received) -> bool:
        msg = r.message
        return isinstance(msg, EncoderSample) and bool(msg.inputs & Inputs.HOME) == closed

    return accept


def reply_state(reply: Any) -> int | None:
    """The state an ACK or NAK reports."""
    return getattr(reply, "state", None)
