"""Checks of batched telemetry (PROTOCOL.md §14): negotiated, bounded in age, flushed when off.

A controller that does not offer `Capability.BATCHED_TELEMETRY` must still send single samples
whatever the host offers (R-BATCH-1, always checked); the checks of how it batches are then
not applicable and reported as skipped.
"""

from __future__ import annotations

import asyncio
import itertools

from host.conformance.base import Context, check, expect, expect_ack
from host.conformance.wire import NotApplicable
from host.link.batches import BATCH_TYPES, unpack
from protocol import ParamId, Stream
from protocol.enums import Capability
from protocol.messages import (
    EncoderBatch,
    EncoderSample,
    HeadSample,
    RangeSample,
    StreamSet,
)

BATCHED = int(Capability.BATCHED_TELEMETRY)
SINGLES = (EncoderSample, RangeSample, HeadSample)
SAMPLE_S = 0.6
TICK_US = 1_000  # slack for the control tick on which a batch's age is checked
_U32 = 0xFFFF_FFFF


async def _streams(ctx: Context, rates: dict[Stream, int]) -> None:
    """STREAM_SET each stream; ConformanceError if one is refused."""
    for stream, rate in rates.items():
        reply = await ctx.client.request(StreamSet(int(stream), rate))
        expect_ack(reply, f"STREAM_SET {stream.name} {rate}")


def _kinds(ctx: Context, mark: int) -> set[type]:
    """Message types of the telemetry received after `mark`."""
    batches_or_singles = (*BATCH_TYPES, *SINGLES)
    return {type(r.message) for r in ctx.client.received[mark:]} & set(batches_or_singles)


async def _batching_session(ctx: Context) -> None:
    """A fresh controller in a session that offers batching; skipped if the controller can't."""
    await ctx.fresh()
    ident = await ctx.client.hello(capabilities=BATCHED)
    if not ident.capabilities & BATCHED:
        raise NotApplicable("the controller does not offer BATCHED_TELEMETRY")


@check("samples come alone unless both sides offer batching", "R-BATCH-1")
async def negotiated(ctx: Context) -> None:
    await ctx.fresh()  # HELLO without capabilities
    c = ctx.client
    rates = {Stream.ENCODER: 100, Stream.RANGE: 50, Stream.HEAD: 50}
    await _streams(ctx, rates)
    mark = c.mark()
    await asyncio.sleep(SAMPLE_S)
    kinds = _kinds(ctx, mark)
    names = sorted(k.__name__ for k in kinds)
    expect(kinds == set(SINGLES), f"a host without batching got {names}")
    ident = await c.hello(capabilities=BATCHED)  # a new session that offers it
    await asyncio.sleep(0.1)  # samples taken before it may still be on their way
    mark = c.mark()
    await asyncio.sleep(SAMPLE_S)
    kinds = _kinds(ctx, mark)
    await _streams(ctx, dict.fromkeys(rates, 0))
    expected = set(BATCH_TYPES) if ident.capabilities & BATCHED else set(SINGLES)
    names = sorted(k.__name__ for k in kinds)
    expect(kinds == expected, f"both offering batching: got {names}")


@check("a batch goes when full, at its age, or alone with age 0", "R-BATCH-2")
async def bounded(ctx: Context) -> None:
    await _batching_session(ctx)
    c = ctx.client
    await ctx.set_param(ParamId.ENCODER_BATCH_AGE_MS, 1_000)
    batches = await _encoder_batches(ctx, 200)
    counts = [len(b.steps) + 1 for b in batches]
    expect(len(batches) >= 5, f"{len(batches)} ENCODER_BATCH in {SAMPLE_S} s at 200 Hz")
    expect(all(n == 7 for n in counts[1:-1]), f"with a long age batches must be full: {counts}")
    age_ms = 30
    await ctx.set_param(ParamId.ENCODER_BATCH_AGE_MS, age_ms)
    batches = await _encoder_batches(ctx, 100)
    spans = [_span_us(b) for b in batches[1:]]
    expect(len(spans) >= 5, f"{len(spans)} ENCODER_BATCH in {SAMPLE_S} s at 100 Hz")
    expect(max(spans) <= age_ms * 1000 + TICK_US, f"a batch spans {max(spans)} µs > {age_ms} ms")
    expect(sum(len(b.steps) for b in batches) >= len(batches), "batches of one: nothing waits")
    samples = [s for b in batches for s in unpack(b)]
    steps = [(b.mcu_time_us - a.mcu_time_us) & _U32 for a, b in itertools.pairwise(samples)]
    expect(all(8_000 <= dt <= 12_000 for dt in steps), f"100 Hz samples {sorted(set(steps))} µs")
    await ctx.set_param(ParamId.ENCODER_BATCH_AGE_MS, 0)
    mark = c.mark()
    await _streams(ctx, {Stream.ENCODER: 100})
    await asyncio.sleep(SAMPLE_S / 2)
    await _streams(ctx, {Stream.ENCODER: 0})
    kinds = _kinds(ctx, mark)
    expect(kinds == {EncoderSample}, f"age 0 must send samples alone: {kinds}")


@check("switching a stream off sends the samples waiting in its batch", "R-BATCH-3")
async def flushed(ctx: Context) -> None:
    await _batching_session(ctx)
    c = ctx.client
    await ctx.set_param(ParamId.ENCODER_BATCH_AGE_MS, 1_000)
    mark = c.mark()
    await _streams(ctx, {Stream.ENCODER: 20})  # a full batch would take 350 ms
    await asyncio.sleep(0.12)
    await _streams(ctx, {Stream.ENCODER: 0})
    await asyncio.sleep(0.2)
    batches = c.since(mark, EncoderBatch)
    expect(len(batches) == 1, f"expected the waiting samples as one batch, got {len(batches)}")
    expect(1 <= len(batches[0].steps) + 1 < 7, f"batch of {len(batches[0].steps) + 1} samples")


async def _encoder_batches(ctx: Context, rate_hz: int) -> list[EncoderBatch]:
    """ENCODER_BATCHes received while the stream runs for SAMPLE_S (then off)."""
    c = ctx.client
    mark = c.mark()
    await _streams(ctx, {Stream.ENCODER: rate_hz})
    await asyncio.sleep(SAMPLE_S)
    await _streams(ctx, {Stream.ENCODER: 0})
    await asyncio.sleep(0.1)
    return c.since(mark, EncoderBatch)


def _span_us(batch: EncoderBatch) -> int:
    """MCU time from a batch's first sample to its last."""
    return sum(s.dt_us for s in batch.steps)
