"""Checks of quiet clock probes (PROTOCOL.md §8, R-QUIET-1): negotiated, held, bounded.

The checks read the order in which frames arrive and the controller's own stamps, never the
host's clock: a sample stamped after a probe arrived but received before that probe's reply
was not held. A controller that does not offer `Capability.QUIET_CLOCK_PROBES` must hold
nothing whatever the host offers (checked always); the hold itself is then not applicable.
"""

from __future__ import annotations

import asyncio
import itertools

from host.conformance.base import Context, check, expect, expect_ack
from host.conformance.wire import NotApplicable, Received
from protocol import Stream
from protocol.enums import Capability
from protocol.messages import ClockSync, ClockSyncReply, EncoderSample, StreamSet
from protocol.schema import QUIET_HOLD_US, Flag

QUIET = int(Capability.QUIET_CLOCK_PROBES)
ENCODER_HZ = 500  # one sample every 2 ms: a hold shows as a run of samples behind a reply
GAP_S = 0.012  # host wait between the two probes of a pair (well inside the 40 ms hold)
SLACK_US = 5_000  # a sample this long before a reply was written has surely been sent
REPLY_TIMEOUT_S = 2.0
ATTEMPTS = 5  # a pair the host could not send inside the hold (a loaded machine) is retried
_U32 = 0xFFFF_FFFF
_tokens = itertools.count(0x5100)


def _after(a_us: int, b_us: int) -> int:
    """Signed µs from a to b on the wrapping 32-bit clock."""
    d = (b_us - a_us) & _U32
    return d - (1 << 32) if d >= 1 << 31 else d


async def _probe(ctx: Context) -> tuple[ClockSyncReply, int]:
    """Send one CLOCK_SYNC; its reply and its index among the received frames."""
    c = ctx.client
    token = next(_tokens) & _U32
    mark = c.mark()
    c.send(ClockSync(token), c.seq, Flag.NONE)
    found = await c.wait_for(
        lambda r: isinstance(r.message, ClockSyncReply) and r.message.token == token,
        REPLY_TIMEOUT_S,
        mark,
    )
    assert found is not None
    return found.message, c.received.index(found, mark)


def _samples(frames: list[Received]) -> list[int]:
    """MCU times of the encoder samples among the frames."""
    return [r.message.mcu_time_us for r in frames if isinstance(r.message, EncoderSample)]


async def _pair(ctx: Context) -> tuple[ClockSyncReply, ClockSyncReply, int]:
    """Two probes GAP_S apart; both replies and the second's index (retried until the second
    arrived inside the first's hold and not too soon after it to tell)."""
    for _ in range(ATTEMPTS):
        first, _ = await _probe(ctx)
        await asyncio.sleep(GAP_S)
        second, index = await _probe(ctx)
        apart = _after(first.rx_time_us, second.rx_time_us)
        if 2 * SLACK_US <= apart < QUIET_HOLD_US:
            return first, second, index
        await asyncio.sleep(0.1)  # a hold in the way ends first
    raise NotApplicable(f"no probe pair arrived 10-40 ms apart in {ATTEMPTS} tries")


async def _session(ctx: Context, capabilities: int) -> int:
    """A fresh session offering `capabilities`, the encoder stream on; the agreed bits."""
    await ctx.fresh()
    ident = await ctx.client.hello(capabilities=capabilities)
    expect_ack(await ctx.client.request(StreamSet(int(Stream.ENCODER), ENCODER_HZ)), "STREAM_SET")
    await asyncio.sleep(0.1)
    return int(ident.capabilities) & capabilities


async def _encoder_off(ctx: Context) -> None:
    expect_ack(await ctx.client.request(StreamSet(int(Stream.ENCODER), 0)), "STREAM_SET off")


@check("quiet probes hold telemetry between the pair, at most 40 ms, only if agreed", "R-QUIET-1")
async def quiet_probes(ctx: Context) -> None:
    c = ctx.client
    # A host that does not offer it: nothing is held, the samples between two probes flow.
    await _session(ctx, 0)
    mark = c.mark()
    first, second, index = await _pair(ctx)
    before = [t for t in _samples(c.received[mark:index]) if _after(first.rx_time_us, t) > 0]
    late = [t for t in before if _after(t, second.rx_time_us) > SLACK_US]
    expect(bool(late), "without QUIET_CLOCK_PROBES the samples between two probes must not wait")
    await _encoder_off(ctx)
    if not await _session(ctx, QUIET):
        await _encoder_off(ctx)
        raise NotApplicable("the controller does not offer QUIET_CLOCK_PROBES")
    # A pair: no sample taken after the first probe arrived comes before the second's reply,
    # and none is lost: they follow it.
    mark = c.mark()
    first, second, index = await _pair(ctx)
    await asyncio.sleep(0.1)
    held = [t for t in _samples(c.received[mark:index]) if _after(first.rx_time_us, t) > 0]
    expect(not held, f"{len(held)} samples taken during the hold came before the second reply")
    after = _samples(c.received[index:])
    between = [
        t
        for t in after
        if 0 < _after(first.rx_time_us, t) < _after(first.rx_time_us, second.rx_time_us)
    ]
    expect(len(between) >= 2, "the samples taken during the hold must follow it, not be dropped")
    # A first probe alone (its pair lost): telemetry flows again 40 ms after it arrived.
    mark = c.mark()
    lone, _ = await _probe(ctx)
    await asyncio.sleep(3 * QUIET_HOLD_US / 1e6)
    later, index = await _probe(ctx)
    expect(
        _after(lone.rx_time_us, later.rx_time_us) > QUIET_HOLD_US + 4 * SLACK_US,
        "the probe after a lone one arrived too soon to tell",
    )
    sent = [
        t
        for t in _samples(c.received[mark:index])
        if _after(lone.rx_time_us, t) > QUIET_HOLD_US + SLACK_US
        and _after(t, later.rx_time_us) > SLACK_US
    ]
    expect(bool(sent), f"telemetry still held {QUIET_HOLD_US} µs after a lone probe")
    await _encoder_off(ctx)
