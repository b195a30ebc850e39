"""The daemon's stream rates fit their links with room left for commands.

Frame sizes come from the codec (COBS adds a fixed byte or two, whatever the values), the
XBee air's rate and per-packet overhead from its emulator, the clock-sync rate from the session
(its converged rate once the fit holds), and batches from the firmware's own batcher run over
a second of ticks at each stream's rate and its link's batch age.
"""

from __future__ import annotations

import pytest

from firmware.batching import Batcher, Sample
from hil_sim.links.endpoint import build
from hil_sim.links.pacing import uart_rate_bytes_s
from hil_sim.links.xbee import AIR_OVERHEAD_BYTES, AIR_RATE_BPS
from host.link.batches import BATCH_AGES_MS
from host.link.session import SessionConfig
from host.service.wiring import stream_rates
from protocol import PARAMS_BY_ID, ParamId, encode_frame
from protocol.enums import Stream
from protocol.messages import (
    ClockSync,
    ClockSyncReply,
    EncoderSample,
    HeadSample,
    Heartbeat,
    RangeSample,
)
from protocol.messages import Status as StatusMsg

MAX_SHARE = 0.70  # the rest is for commands, their replies, retransmissions and MAC retries
SAMPLES = {
    Stream.ENCODER: build(EncoderSample, 0, 0, 0, 0, 0),
    Stream.RANGE: build(RangeSample, 0, 0, 0),
    Stream.HEAD: build(HeadSample, 0, 0, 0),
    Stream.STATUS: build(StatusMsg, 0, 0, 0, 0, 0, 0),
}
PROBE_HZ = 1.0 / SessionConfig().clock_sync_interval_s
CONVERGED_PROBE_HZ = 1.0 / SessionConfig().clock_sync_slow_interval_s
TICK_US = 1_000
# The host's heartbeats fill its silences every WATCHDOG_MS / 4 (PROTOCOL.md §9), at the default.
HEARTBEAT_HZ = 4000 / PARAMS_BY_ID[ParamId.WATCHDOG_MS].default


def _sample(stream: Stream, t_us: int, i: int) -> Sample:
    """The i-th sample of a stream at MCU time t_us: a trolley at ~100 mm/s."""
    if stream == Stream.ENCODER:
        return EncoderSample(t_us, 16 * i, 13 * i, 1575, 0x10)
    if stream == Stream.RANGE:
        return RangeSample(t_us, 4_000_000 - 5 * i, 200)
    return HeadSample(t_us, 100 * i, 0)


def batched_bytes_per_s(stream: Stream, rate_hz: int, age_ms: int, overhead: int) -> float:
    """Wire bytes (+ per-packet overhead) one stream sends per second, batched as the firmware."""
    if age_ms == 0 or stream not in (Stream.ENCODER, Stream.RANGE, Stream.HEAD):
        return rate_hz * (_frame(SAMPLES[stream]) + overhead)
    batcher, acc, sent, total = Batcher(), 0, 0, 0
    for tick in range(1_000):
        now = tick * TICK_US
        acc += rate_hz
        batches = []
        if acc >= 1_000:
            acc -= 1_000
            batches += batcher.add(_sample(stream, now, sent))
            sent += 1
        due = batcher.due(now, age_ms * 1000)
        batches += [due] if due is not None else []
        total += sum(_frame(b) + overhead for b in batches)
    return float(total)


def _frame(message: object) -> int:
    """Wire bytes of one frame, delimiter included."""
    return len(encode_frame(message, 0))


def _probe_pair(overhead: int) -> int:
    """A clock probe and its reply, with the per-packet overhead."""
    return _frame(build(ClockSync, 0)) + _frame(build(ClockSyncReply, 0, 0, 0, 0)) + 2 * overhead


@pytest.mark.parametrize("ranging", [False, True])
def test_xbee_batched_streams_leave_a_third_of_the_air(ranging: bool) -> None:
    """One half-duplex channel for both ways; every frame is an RF packet with its overhead."""
    ages = BATCH_AGES_MS["xbee"]
    rates = stream_rates("xbee", ranging)
    load = sum(
        batched_bytes_per_s(stream, rate, ages.get(stream, 0), AIR_OVERHEAD_BYTES)
        for stream, rate in rates.items()
    )
    load += CONVERGED_PROBE_HZ * _probe_pair(AIR_OVERHEAD_BYTES)
    load += HEARTBEAT_HZ * (_frame(build(Heartbeat, 0)) + AIR_OVERHEAD_BYTES)
    share = load / (AIR_RATE_BPS / 8)
    assert share <= MAX_SHARE, f"XBee streams take {share:.0%} of the air"
    assert rates[Stream.ENCODER] >= 100
    assert not ranging or rates[Stream.RANGE] >= 50


@pytest.mark.parametrize("ranging", [False, True])
def test_xbee_single_sample_streams_leave_a_third_of_the_air(ranging: bool) -> None:
    """A controller that does not batch: every sample its own packet, probes at full rate."""
    rates = stream_rates("xbee", ranging, batched=False)
    load: float = sum(
        rate * (_frame(SAMPLES[stream]) + AIR_OVERHEAD_BYTES) for stream, rate in rates.items()
    )
    load += PROBE_HZ * _probe_pair(AIR_OVERHEAD_BYTES)
    share = load / (AIR_RATE_BPS / 8)
    assert share <= MAX_SHARE, f"XBee streams take {share:.0%} of the air"


@pytest.mark.parametrize("ranging", [False, True])
def test_serial_streams_leave_a_third_of_the_line(ranging: bool) -> None:
    """Full duplex: the controller's direction carries the telemetry and the clock replies."""
    rates = stream_rates("serial", ranging)
    load: float = sum(rate * _frame(SAMPLES[stream]) for stream, rate in rates.items())
    load += PROBE_HZ * _frame(build(ClockSyncReply, 0, 0, 0, 0))
    share = load / uart_rate_bytes_s(115200)
    assert share <= MAX_SHARE, f"serial streams take {share:.0%} of the line"
