"""Checks of the link rules: framing, NAKs, ordering, duplicate memory, handshake, versions."""

from __future__ import annotations

import asyncio
import itertools
import time

from host.conformance.base import (
    ACCEL_UM_S2,
    JOG_UM_S,
    Context,
    check,
    expect,
    expect_ack,
    expect_nak,
    raw_command,
    raw_wire,
)
from protocol import SCHEMA, Flag, NakCode, ParamId, State, Stream, cobs, encode_frame
from protocol.codec import encode_payload
from protocol.compat import encode_v1
from protocol.crc import frame_crc
from protocol.messages import (
    ClockSync,
    ClockSyncReply,
    EncoderSample,
    Estop,
    Heartbeat,
    Hello,
    Identify,
    Jog,
    MoveTo,
    ParamGet,
    ParamSet,
    ParamValue,
    Reset,
    Status,
    Stop,
    StreamSet,
)

SILENCE_S = 0.15  # how long "no reply" is waited for
UNKNOWN_ID = 0x7E
ACKED = Flag.ACK_REQUESTED
TEST_PARAM = ParamId.HOME_SPEED_UM_S
CHUNK_BYTES = 64


async def _value(ctx: Context) -> int:
    """TEST_PARAM's value in force."""
    return await ctx.param(TEST_PARAM)


# ---- framing -------------------------------------------------------------------------


@check("idle fill and oversize frames are harmless", "R-FRAME-1", "R-FRAME-3")
async def idle_and_oversize(ctx: Context) -> None:
    await ctx.fresh()
    oversize = b"\x00" * 8 + bytes(range(1, 201)) + b"\x00\x00"
    for i in range(0, len(oversize), CHUNK_BYTES):  # datagram links carry at most one frame
        ctx.client.send_raw(oversize[i : i + CHUNK_BYTES])
    reply = await ctx.client.request(ParamGet(int(TEST_PARAM)))
    expect(isinstance(reply, ParamValue), f"after idle fill and an oversize frame: {reply!r}")


@check("a frame with zeros appended or its last byte removed is dropped", "R-FRAME-2")
async def trailing_zeros(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    before = await _value(ctx)
    for cut in ("append", "append2", "remove"):
        seq = c.seq  # the damaged frame must not take the turn: the good one reuses the seq
        raw = cobs.decode(encode_frame(ParamSet(int(TEST_PARAM), before + 7), seq, ACKED)[:-1])
        damaged = {"append": raw + b"\x00", "append2": raw + b"\x00\x00", "remove": raw[:-1]}[cut]
        c.send_raw(cobs.encode(damaged) + b"\x00")
        expect(await c.replies_to(seq, SILENCE_S, c.mark()) == [], f"damaged ({cut}) answered")
        expect(await _value(ctx) == before, f"a damaged PARAM_SET ({cut}) took effect")


@check("unknown header flag bits are ignored", "R-FLAGS-1")
async def unknown_flags(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    seq = c.take_seq()
    c.send(ParamGet(int(TEST_PARAM)), seq, ACKED | 0xF0)
    reply = await c.wait_reply(seq, 1.0)
    expect(isinstance(reply, ParamValue), f"flags 0xF1 on PARAM_GET: {reply!r}")


# ---- NAKs ----------------------------------------------------------------------------


@check("an acked unknown id or bad payload is NAKed in turn", "R-NAK-1")
async def nak_unknown_and_payload(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    seq = c.take_seq()
    c.send_raw(raw_wire(UNKNOWN_ID, b"\x01\x02", seq), seq)
    expect_nak(await c.wait_reply(seq, 1.0), NakCode.UNKNOWN_MESSAGE, what="unknown id")
    seq = c.take_seq()
    c.send_raw(raw_wire(SCHEMA.by_cls[ParamSet].id, b"\x01\x00", seq), seq)
    expect_nak(await c.wait_reply(seq, 1.0), NakCode.BAD_PAYLOAD, what="short PARAM_SET")
    expect(isinstance(await c.request(ParamGet(1)), ParamValue), "the sequence went on")


@check("NAKs come in the documented check order and change nothing", "R-NAK-2", "R-NAK-3")
async def nak_order(ctx: Context) -> None:
    c = ctx.client
    await c.request(Reset())
    await asyncio.sleep(0.3)
    seq = c.take_seq()
    c.send_raw(raw_wire(UNKNOWN_ID, b"", seq), seq)
    expect_nak(await c.wait_reply(seq, 1.0), NakCode.HELLO_REQUIRED, what="before HELLO")
    await c.hello()
    before = await _value(ctx)
    for reply, code in (
        (await c.request(ParamSet(999, 1 << 30)), NakCode.UNKNOWN_PARAM),
        (await c.request(ParamSet(int(TEST_PARAM), 1)), NakCode.OUT_OF_RANGE),
        (await c.request(MoveTo(-100_000_000, 1000, 1000)), NakCode.NOT_HOMED),
    ):
        expect_nak(reply, code, State.IDLE)
    expect(await _value(ctx) == before, "a NAKed PARAM_SET changed the parameter")
    expect_ack(await c.request(Estop()), "ESTOP")
    seq = c.take_seq()
    c.send_raw(raw_command(Jog(3_000_000, 1000), seq), seq)  # out of range AND in the wrong state
    expect_nak(await c.wait_reply(seq, 1.0), NakCode.OUT_OF_RANGE, what="range before state")
    expect_nak(
        await c.request(MoveTo(1000, 1000, 1000)), NakCode.BAD_STATE, State.ESTOP, "state first"
    )


# ---- ordering ------------------------------------------------------------------------


@check("a command ahead of a gap waits for it, then both run in order", "R-ORDER-1")
async def held_until_gap_fills(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    base = await _value(ctx)
    first, second = c.take_seq(), c.take_seq()
    c.send(ParamSet(int(TEST_PARAM), base + 2), second)  # as if `first` had been lost
    expect(await c.replies_to(second, SILENCE_S, c.mark()) == [], "ran ahead of its gap")
    mark = c.mark()
    c.send(ParamSet(int(TEST_PARAM), base + 1), first)  # the retransmission arrives
    got_first = await c.wait_reply(first, 1.0, mark)
    got_second = await c.wait_reply(second, 1.0, mark)
    expect(isinstance(got_first, ParamValue), f"gap filler: {got_first!r}")
    expect(isinstance(got_second, ParamValue), f"held command: {got_second!r}")
    order = [getattr(r.message, "req_seq", None) for r in c.received[mark:]]
    expect(order.index(first) < order.index(second), "replies out of sequence order")
    final = await _value(ctx)
    expect(final == base + 2, f"the later command must take effect last: {final}")


@check("a command too far ahead is BUSY and not remembered", "R-ORDER-2")
async def too_far_ahead(ctx: Context) -> None:
    ident = await _fresh_ident(ctx)
    c = ctx.client
    far = (c.seq + ident.rx_window + 1) % (1 << 16)
    c.send(ParamGet(int(TEST_PARAM)), far)
    expect_nak(await c.wait_reply(far, 1.0), NakCode.BUSY, what="beyond the window")
    expect(isinstance(await c.request(ParamGet(1)), ParamValue), "the sequence went on")


async def _fresh_ident(ctx: Context) -> Identify:
    """A fresh session's IDENTIFY."""
    await ctx.fresh()
    assert ctx.client.identity is not None
    return ctx.client.identity


@check("STOP runs ahead of a gap and cancels older commands", "R-ORDER-3", motion=True)
async def stop_cancels(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    lost, held, stop = c.take_seq(), c.take_seq(), c.take_seq()
    mark = c.mark()
    c.send(Jog(JOG_UM_S, ACCEL_UM_S2), held)
    c.send(Stop(), stop)
    expect_ack(await c.wait_reply(stop, 1.0, mark), "STOP ahead of a gap")
    expect_nak(await c.wait_reply(held, 1.0, mark), NakCode.STALE_SEQ, what="held before STOP")
    c.send(Jog(-JOG_UM_S, ACCEL_UM_S2), lost)
    expect_nak(await c.wait_reply(lost, 1.0, mark), NakCode.STALE_SEQ, what="lost before STOP")
    await asyncio.sleep(0.1)
    reply = await c.request(ParamGet(1))
    expect(isinstance(reply, ParamValue), f"{reply!r}")
    expect(not [s for s in c.since(mark, Status) if s.state == State.MOVING], "it moved")


@check("a seq behind the sequence and not remembered is STALE_SEQ", "R-ORDER-4")
async def stale(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    before = await _value(ctx)
    old = (c.seq - 40) % (1 << 16)
    c.send(ParamSet(int(TEST_PARAM), before + 3), old)
    expect_nak(await c.wait_reply(old, 1.0), NakCode.STALE_SEQ, what="40 behind")
    expect(await _value(ctx) == before, "a stale command took effect")


@check("unacked frames take no place in the sequence", "R-ORDER-5")
async def unacked(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    before = await _value(ctx)
    seq = c.seq  # none of the three below may spend it
    mark = c.mark()
    c.send(ParamSet(int(TEST_PARAM), before + 4), seq, Flag.NONE)  # acked-only, no flag
    c.send(Heartbeat(1), seq, ACKED)
    c.send(ClockSync(77), seq, ACKED)
    await asyncio.sleep(SILENCE_S)
    answers = [r.message for r in c.received[mark:] if getattr(r.message, "req_seq", -1) == seq]
    clock = [m for m in answers if isinstance(m, ClockSyncReply)]
    expect(len(clock) == 1 and clock[0].token == 77, "CLOCK_SYNC with ACK_REQUESTED: one reply")
    expect(len(answers) == 1, f"unacked frames answered as commands: {answers!r}")
    value = await ctx.client.request(ParamGet(int(TEST_PARAM)), seq)  # the seq is still next
    expect(isinstance(value, ParamValue), f"the next command after them: {value!r}")
    expect(value.value == before, "a PARAM_SET without ACK_REQUESTED ran")
    c.seq = (seq + 1) % (1 << 16)


# ---- duplicate memory ----------------------------------------------------------------


@check("a repeat gets its reply again and does not run twice", "R-DUP-1")
async def duplicate(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    base = await _value(ctx)
    seq = c.take_seq()
    first = await c.request(ParamSet(int(TEST_PARAM), base + 5), seq)
    await ctx.set_param(TEST_PARAM, base + 6)
    mark = c.mark()
    c.send(ParamSet(int(TEST_PARAM), base + 5), seq, ACKED | Flag.RETRANSMIT)
    again = await c.wait_reply(seq, 1.0, mark)
    expect(again == first, f"re-sent reply differs: {again!r} != {first!r}")
    expect(await _value(ctx) == base + 6, "the repeat ran again")


@check("a remembered seq with other content is refused", "R-DUP-2")
async def reused_seq(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    base = await _value(ctx)
    seq = c.take_seq()
    await c.request(ParamSet(int(TEST_PARAM), base + 5), seq)
    mark = c.mark()
    c.send(ParamSet(int(TEST_PARAM), base + 9), seq)
    expect_nak(await c.wait_reply(seq, 1.0, mark), NakCode.STALE_SEQ, what="other content")
    expect(await _value(ctx) == base + 5, "the other content ran")


# ---- handshake, versions, reset --------------------------------------------------------


@check("before HELLO only HELLO, STOP and ESTOP are executed", "R-HELLO-1")
async def hello_required(ctx: Context) -> None:
    c = ctx.client
    await c.request(Reset())
    await asyncio.sleep(0.3)
    expect_nak(await c.request(ParamGet(1)), NakCode.HELLO_REQUIRED, what="PARAM_GET")
    expect_ack(await c.request(Stop()), "STOP before HELLO")
    expect_ack(await c.request(Estop()), "ESTOP before HELLO")
    await c.hello()


@check("a repeated HELLO resets nothing; a new one starts afresh", "R-HELLO-2")
async def hello_repeat(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    hello_seq = (c.seq - 1) % (1 << 16)
    seq = c.take_seq()
    first = await c.request(ParamGet(int(TEST_PARAM)), seq)
    mark = c.mark()
    hello_again = Hello(*_hello_fields(ctx))
    c.send(hello_again, hello_seq)
    ident = await c.wait_reply(hello_seq, 1.0, mark)
    expect(isinstance(ident, Identify), f"repeated HELLO: {ident!r}")
    again = await c.request(ParamGet(int(TEST_PARAM)), seq)
    expect(again == first, "a repeated HELLO cleared the duplicate memory")
    c.session_id ^= 0x5A5A_5A5A
    await c.hello()
    expect(isinstance(await c.request(ParamGet(1)), ParamValue), "new session's sequence")


def _hello_fields(ctx: Context) -> tuple[int, int, int, int]:
    """The fields of the HELLO this client opened its session with."""
    from protocol import PROTOCOL_VERSION, SCHEMA_HASH

    return PROTOCOL_VERSION, SCHEMA_HASH, 0, ctx.client.session_id


@check("HELLO of other versions is answered and opens no session", "R-VER-1")
async def versions(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    mark = c.mark()
    c.send_raw(encode_v1(Hello(1, 0x1234_5678), 4242, ACKED))
    v1 = await c.wait_for(lambda r: getattr(r.message, "req_seq", None) == 4242, 1.0, mark)
    assert v1 is not None
    expect(isinstance(v1.message, Identify), f"v1 HELLO answered {v1.message!r}")
    expect(v1.packet.version == 1, "a v1 HELLO must be answered in v1 framing")
    body = Hello(3, 0xABCD_EF01, 0, 1)
    header = bytes([3, ACKED]) + (4343).to_bytes(2, "little") + bytes([SCHEMA.by_cls[Hello].id])
    raw = header + _payload(body) + b"\x99\x98\x97\x96"
    c.send_raw(cobs.encode(raw + frame_crc(raw).to_bytes(2, "big")) + b"\x00")
    v3 = await c.wait_reply(4343, 1.0, mark)
    expect(isinstance(v3, Identify), f"v3 HELLO (longer) answered {v3!r}")
    expect(isinstance(await c.request(ParamGet(1)), ParamValue), "a foreign HELLO reset us")


def _payload(msg: object) -> bytes:
    """A message's payload bytes."""
    return encode_payload(msg)[1]


@check("unknown capability bits are ignored", "R-VER-2")
async def capabilities(ctx: Context) -> None:
    c = ctx.client
    await c.request(Reset())
    await asyncio.sleep(0.3)
    ident = await c.hello(capabilities=0xFFFF_FFFF)
    expect(ident.capabilities >= 0, "IDENTIFY carries capabilities")
    expect(isinstance(await c.request(ParamGet(1)), ParamValue), "session with every bit set")


@check("RESET reboots: new boot id, seq from 0, IDLE, streams off", "R-RESET-1")
async def reset(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    assert c.identity is not None
    old_boot = c.identity.boot_id
    expect_ack(await c.request(StreamSet(int(Stream.ENCODER), 50)), "STREAM_SET")
    mark = c.mark()
    expect_ack(await c.request(Reset()), "RESET")
    await asyncio.sleep(0.3)
    expect_nak(await c.request(ParamGet(1)), NakCode.HELLO_REQUIRED, what="after RESET")
    after = [r for r in c.received[mark:] if not isinstance(r.message, ClockSyncReply)]
    expect(any(r.packet.seq < 4 for r in after[1:]), "controller seq restarted from 0")
    ident = await c.hello()
    expect(ident.boot_id != old_boot, "boot_id unchanged by RESET")
    expect(ident.state == State.IDLE, f"state after RESET: {ident.state}")
    mark = c.mark()
    await asyncio.sleep(0.2)
    expect(not c.since(mark, EncoderSample), "streams still on after RESET")


@check("every controller frame takes the next seq; heartbeat when quiet", "R-SEQ-1", "R-HB-1")
async def seq_and_heartbeat(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    mark = c.mark()
    for _ in range(10):
        await c.request(ParamGet(1))
    await asyncio.sleep(0.7)
    frames = c.received[mark:]
    seqs = [r.packet.seq for r in frames]
    gaps = [(a, b) for a, b in itertools.pairwise(seqs) if (b - a) % (1 << 16) != 1]
    expect(not gaps, f"controller seq not consecutive on a clean link: {gaps[:3]}")
    times = [r.at_s for r in frames] + [time.monotonic()]
    longest = max(b - a for a, b in itertools.pairwise(times))
    expect(longest < 0.4, f"controller silent for {longest:.2f} s (heartbeat after 250 ms)")
    expect(bool(c.since(mark, Heartbeat)), "no controller HEARTBEAT in 0.7 s of quiet")


@check("streams beyond the link's rate drop telemetry, never replies", "R-STREAM-1")
async def back_pressure(ctx: Context) -> None:
    await ctx.fresh()
    c = ctx.client
    try:
        for stream in Stream:
            reply = await c.request(StreamSet(int(stream), 1000))
            expect_ack(reply, f"STREAM_SET {stream.name}")
        await asyncio.sleep(0.5)  # let any queue fill
        worst = 0.0
        for _ in range(10):
            t0 = time.monotonic()
            reply = await c.request(ParamGet(1), timeout_s=2.0)
            worst = max(worst, time.monotonic() - t0)
            expect(isinstance(reply, ParamValue), f"reply under load: {reply!r}")
    finally:
        for stream in Stream:
            await c.request(StreamSet(int(stream), 0), timeout_s=2.0)
    expect(worst < 0.5, f"a reply waited {worst:.2f} s behind telemetry")
