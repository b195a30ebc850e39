"""Batched telemetry on the host: each batch back into the single samples it carries.

A batch (ENCODER_BATCH, RANGE_BATCH, HEAD_BATCH; PROTOCOL.md §14) holds its first sample in
full and every later one as steps from the sample before it. `unpack` rebuilds the samples,
each with its own MCU time (mod 2³², so a batch may cross the counter's wrap), so that the
controller API feeds them to the same buffers as single samples: the drift filter and the
pose buffers see only more samples. A batch that is cut short or damaged on the way fails the
frame check and is dropped as a whole by the decoder (counted there and, through its seq, as a
lost frame); `BatchStats` counts what arrived.
"""

from __future__ import annotations

from dataclasses import dataclass

from protocol import ParamId
from protocol.enums import Stream
from protocol.messages import (
    EncoderBatch,
    EncoderSample,
    HeadBatch,
    HeadSample,
    RangeBatch,
    RangeSample,
)

Sample = EncoderSample | RangeSample | HeadSample
Batch = EncoderBatch | RangeBatch | HeadBatch
BATCH_TYPES = (EncoderBatch, RangeBatch, HeadBatch)

_U32 = 0xFFFF_FFFF
_U32_MOD = 1 << 32
_I32_HALF = 1 << 31


def _i32(x: int) -> int:
    """Wrap to a signed 32-bit value, as the sample's int32 fields are."""
    return ((x + _I32_HALF) & _U32) - _I32_HALF


@dataclass
class BatchStats:
    """What arrived in batches, per kind."""

    batches: int = 0
    samples: int = 0
    encoder_samples: int = 0
    range_samples: int = 0
    head_samples: int = 0


def unpack_encoder(batch: EncoderBatch) -> list[EncoderSample]:
    """The ENCODER_SAMPLEs of a batch, oldest first."""
    t, enc, steps = batch.mcu_time_us, batch.encoder_count, batch.step_count
    vel = batch.velocity_counts_s
    out = [EncoderSample(t, enc, steps, vel, batch.inputs)]
    for s in batch.steps:
        t = (t + s.dt_us) & _U32
        enc, steps = _i32(enc + s.encoder_step), _i32(steps + s.step_step)
        vel = _i32(vel + s.velocity_step)
        out.append(EncoderSample(t, enc, steps, vel, s.inputs))
    return out


def unpack_range(batch: RangeBatch) -> list[RangeSample]:
    """The RANGE_SAMPLEs of a batch, oldest first."""
    t, dist = batch.mcu_time_us, batch.distance_um
    out = [RangeSample(t, dist, batch.quality)]
    for s in batch.steps:
        t = (t + s.dt_us) & _U32
        dist = (dist + s.distance_step) % _U32_MOD
        out.append(RangeSample(t, dist, s.quality))
    return out


def unpack_head(batch: HeadBatch) -> list[HeadSample]:
    """The HEAD_SAMPLEs of a batch, oldest first."""
    t, pan, tilt = batch.mcu_time_us, batch.pan_urad, batch.tilt_urad
    out = [HeadSample(t, pan, tilt)]
    for s in batch.steps:
        t = (t + s.dt_us) & _U32
        pan, tilt = _i32(pan + s.pan_step), _i32(tilt + s.tilt_step)
        out.append(HeadSample(t, pan, tilt))
    return out


def unpack(batch: Batch, stats: BatchStats | None = None) -> list[Sample]:
    """The samples of any batch, oldest first; counted in `stats` when given."""
    samples: list[Sample]
    if isinstance(batch, EncoderBatch):
        samples = list(unpack_encoder(batch))
    elif isinstance(batch, RangeBatch):
        samples = list(unpack_range(batch))
    else:
        samples = list(unpack_head(batch))
    if stats is not None:
        stats.batches += 1
        stats.samples += len(samples)
        if isinstance(batch, EncoderBatch):
            stats.encoder_samples += len(samples)
        elif isinstance(batch, RangeBatch):
            stats.range_samples += len(samples)
        else:
            stats.head_samples += len(samples)
    return samples


# ---- per link: batch ages, and the rates of a controller that does not batch --------------

# How long a stream's oldest sample may wait for its batch to fill, per link (ms; 0 = alone).
# The radio needs few, full packets (host.service.wiring has its budget); a UART pays 7 bytes
# of framing per frame and little time; CAN has room to spare and sends every sample at once.
# HEAD stays alone over XBee: at 10 Hz its time step exceeds a record's 65 ms.
BATCH_AGES_MS: dict[str, dict[Stream, int]] = {
    "serial": {Stream.ENCODER: 5, Stream.RANGE: 5, Stream.HEAD: 20},
    "xbee": {Stream.ENCODER: 40, Stream.RANGE: 60, Stream.HEAD: 0},
    "can": {Stream.ENCODER: 0, Stream.RANGE: 0, Stream.HEAD: 0},
}
BATCH_AGE_PARAMS = {
    Stream.ENCODER: ParamId.ENCODER_BATCH_AGE_MS,
    Stream.RANGE: ParamId.RANGE_BATCH_AGE_MS,
    Stream.HEAD: ParamId.HEAD_BATCH_AGE_MS,
}
# A controller that does not batch sends every sample alone; over XBee the streams then run at
# the single-sample budget (host.service.wiring): without ranging, and what ranging changes.
SINGLE_SAMPLE_RATES_HZ: dict[str, tuple[dict[Stream, int], dict[Stream, int]]] = {
    "xbee": (
        {Stream.ENCODER: 30, Stream.HEAD: 10, Stream.STATUS: 2},
        {Stream.ENCODER: 25, Stream.RANGE: 15},
    ),
}
MAX_AGE_MS = 1_000  # the parameters' ceiling


@dataclass(frozen=True)
class TelemetryPlan:
    """What a link's budget asks of batching: ages when the controller batches, else rates."""

    ages_ms: dict[Stream, int]
    single_rates_hz: tuple[dict[Stream, int], dict[Stream, int]] | None = None

    def age_params(self, scale: float = 1.0) -> dict[int, int]:
        """Parameter id → age; while shedding (scale < 1) batches wait longer, so fewer go."""
        return {
            int(BATCH_AGE_PARAMS[s]): min(MAX_AGE_MS, round(ms / max(scale, 1e-3)))
            for s, ms in self.ages_ms.items()
        }

    def unbatched(self, streams: dict[Stream, int]) -> dict[Stream, int]:
        """The rates to ask of a controller that does not batch, for the streams now wanted."""
        if self.single_rates_hz is None:
            return streams
        base, ranging = self.single_rates_hz
        rates = dict(streams)
        rates.update({s: r for s, r in base.items() if streams.get(s, 0) > 0})
        if streams.get(Stream.RANGE, 0) > 0:
            rates.update(ranging)
        return rates


def plan_for(kind: str) -> TelemetryPlan | None:
    """The plan of a link kind (a transport's scheme); None for one without a budget."""
    if kind not in BATCH_AGES_MS:
        return None
    return TelemetryPlan(BATCH_AGES_MS[kind], SINGLE_SAMPLE_RATES_HZ.get(kind))
