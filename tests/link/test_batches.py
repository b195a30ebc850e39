"""Batched telemetry end to end: the firmware's batcher, the wire, the host's unpacking.

Every sample that goes into a batch comes out of it with its own MCU time and values, at every
boundary (a batch of one, the last of a full batch, the largest steps, the 32-bit MCU time
wrapping inside a batch); a damaged batch loses only itself and is counted; and a controller or
host without the capability falls back to single samples.
"""

from __future__ import annotations

import asyncio

import pytest

from firmware.batching import Batch, Batcher, Sample, max_steps
from host.link.batches import BatchStats, unpack
from host.link.controller import Controller
from host.link.reconnect import BackoffConfig
from host.link.session import Session, SessionConfig
from host.transport.memory import MemoryTransport
from protocol import FrameDecoder, Packet, encode_frame
from protocol.enums import Capability, Stream
from protocol.messages import (
    EncoderBatch,
    EncoderSample,
    HeadBatch,
    HeadSample,
    RangeBatch,
    RangeSample,
)
from tests.link.sim_bridge import SimBridge

WRAP = 1 << 32


def _through_the_wire(samples: list[Sample]) -> tuple[list[Batch], list[Sample]]:
    """Batch the samples as the firmware does, frame, decode, unpack: (batches, samples)."""
    batcher = Batcher()
    batches = [b for s in samples for b in batcher.add(s)]
    tail = batcher.flush()
    batches += [tail] if tail is not None else []
    decoder = FrameDecoder()
    wire = b"".join(encode_frame(b, seq) for seq, b in enumerate(batches))
    received = [p.message for p in decoder.feed(wire)]
    assert received == batches
    assert decoder.drops.total() == 0
    return batches, [s for b in received for s in unpack(b)]  # type: ignore[arg-type]


def _encoder(n: int, t0: int = 1_000, dt: int = 10_000, count: int = 0) -> list[Sample]:
    """n encoder samples of a trolley at ~100 mm/s."""
    return [
        EncoderSample((t0 + i * dt) % WRAP, count + 16 * i, 13 * i, 1575 + i % 3, 0x10)
        for i in range(n)
    ]


def test_a_batch_of_one_is_its_first_sample() -> None:
    batches, out = _through_the_wire(_encoder(1))
    assert out == _encoder(1)
    assert isinstance(batches[0], EncoderBatch)
    assert batches[0].steps == ()


def test_a_full_batch_holds_seven_samples_and_the_eighth_starts_the_next() -> None:
    samples = _encoder(2 * (max_steps(EncoderSample) + 1) + 1)
    batches, out = _through_the_wire(samples)
    assert out == samples
    assert [len(b.steps) for b in batches] == [6, 6, 0]
    assert out[6] == samples[6]
    assert out[7] == samples[7]


def test_every_kind_round_trips_at_its_maximum_count() -> None:
    ranges: list[Sample] = [RangeSample(5 + 20_000 * i, 4_000_000 - 7 * i, 200) for i in range(14)]
    heads: list[Sample] = [HeadSample(9 + 50_000 * i, -1_000 * i, 500 * i) for i in range(11)]
    for samples, cls in ((ranges, RangeBatch), (heads, HeadBatch)):
        batches, out = _through_the_wire(samples)
        assert out == samples
        assert len(batches) == 1
        assert isinstance(batches[0], cls)


def test_largest_steps_fit_and_one_more_starts_a_new_batch() -> None:
    a = EncoderSample(0, 0, 0, 0, 0)
    b = EncoderSample(65_535, 32_767, -32_768, 32_767, 0x3F)  # every step at its limit
    c = EncoderSample(65_536, 32_767, -32_768, 32_767, 0)  # dt 1
    d = EncoderSample(65_536 + 65_536, 32_767, -32_768, 32_767, 0)  # dt 65 536: too long
    e = EncoderSample(65_536 + 65_537, 32_767 + 32_768, -32_768, 32_767, 0)  # +32 768 counts
    batches, out = _through_the_wire([a, b, c, d, e])
    assert out == [a, b, c, d, e]
    assert [len(x.steps) for x in batches] == [2, 0, 0]


def test_mcu_time_wrapping_inside_a_batch() -> None:
    samples = _encoder(5, t0=WRAP - 25_000)  # the counter wraps between the 3rd and 4th
    batches, out = _through_the_wire(samples)
    assert len(batches) == 1
    times = [s.mcu_time_us for s in out]
    assert times == [WRAP - 25_000, WRAP - 15_000, WRAP - 5_000, 5_000, 15_000]


def test_a_batch_is_sent_once_its_oldest_sample_reaches_the_age() -> None:
    batcher = Batcher()
    for s in _encoder(3):
        assert batcher.add(s) == []
    assert batcher.due(1_000 + 29_999, 30_000) is None
    due = batcher.due(1_000 + 30_000, 30_000)
    assert isinstance(due, EncoderBatch)
    assert len(due.steps) == 2
    assert len(batcher) == 0
    # A stream too slow for a record's time step (< ~15 Hz) waits for no later sample.
    batcher.add(HeadSample(0, 0, 0))
    assert batcher.due(65_534, 200_000) is None
    assert isinstance(batcher.due(65_535, 200_000), HeadBatch)


async def test_a_damaged_or_cut_batch_loses_only_itself_and_is_counted() -> None:
    samples = _encoder(7 * 6)
    batcher = Batcher()
    batches = [b for s in samples for b in batcher.add(s)]
    frames = [bytearray(encode_frame(b, 100 + i)) for i, b in enumerate(batches)]
    frames[1][10] ^= 0x04  # one bit flipped
    del frames[3][20:30]  # cut short: ten bytes lost inside the frame
    got: list[object] = []
    session = Session(MemoryTransport(), on_packet=lambda p: got.append(p.message))
    session._on_bytes(b"".join(bytes(f) for f in frames))
    stats = BatchStats()
    out = [s for b in got for s in unpack(b, stats)]  # type: ignore[arg-type]
    assert got == [b for i, b in enumerate(batches) if i not in (1, 3)]
    assert out == samples[:7] + samples[14:21] + samples[28:]
    assert session.stats.drops.total() == 2  # the decoder counted both
    assert session.stats.rx_lost == 2  # and their seqs are gaps
    assert (stats.batches, stats.encoder_samples) == (4, 28)


# ---- negotiation, against the firmware mirror ------------------------------------------------


@pytest.mark.parametrize(
    ("host_caps", "fw_caps", "batched"),
    [
        (int(Capability.BATCHED_TELEMETRY), int(Capability.BATCHED_TELEMETRY), True),
        (0, int(Capability.BATCHED_TELEMETRY), False),  # an older host
        (int(Capability.BATCHED_TELEMETRY), 0, False),  # an older controller
    ],
    ids=["both", "old-host", "old-controller"],
)
async def test_batching_only_when_both_offer_it(
    bridge: SimBridge, host_caps: int, fw_caps: int, batched: bool
) -> None:
    bridge.sim.firmware.capabilities = fw_caps
    config = SessionConfig(rto_initial_s=0.05, capabilities=host_caps)
    ctrl = Controller(bridge.transport, config, BackoffConfig(0.02, 0.2), seed=3)
    frames: list[object] = []
    try:
        await ctrl.connect()

        def seen(packet: Packet) -> None:
            frames.append(packet.message)
            ctrl._on_packet(packet)

        ctrl.session.on_packet = seen
        await ctrl.set_streams({Stream.ENCODER: 200, Stream.RANGE: 100, Stream.HEAD: 50})
        await asyncio.sleep(1.0)
    finally:
        await ctrl.close()
    kinds = {type(m) for m in frames}
    assert bool(ctrl.session.capabilities & Capability.BATCHED_TELEMETRY) is batched
    if batched:
        assert {EncoderBatch, RangeBatch, HeadBatch} <= kinds
        assert not kinds & {EncoderSample, RangeSample, HeadSample}
        assert ctrl.batch_stats.samples > 2 * ctrl.batch_stats.batches
    else:
        assert {EncoderSample, RangeSample, HeadSample} <= kinds
        assert not kinds & {EncoderBatch, RangeBatch, HeadBatch}
    # Either way the samples reach the same buffer, in MCU-time order, ~200 a second.
    times = [t for t, *_ in ctrl.encoder_ring]
    assert times == sorted(times)
    assert len(set(times)) == len(times)
    assert len(times) > 120
