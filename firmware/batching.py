"""Batched telemetry in the controller: collect each stream's samples, send them several a frame.

With Capability.BATCHED_TELEMETRY agreed in the handshake, ENCODER, RANGE and HEAD samples are
not sent one a frame: each stream's samples are collected into a batch (its first sample in
full, every later one as steps from the sample before it) that is sent when it is full, when
the next sample's step does not fit a record's type, or when its oldest sample has waited
BATCH_AGE_MS (PROTOCOL.md §14, R-BATCH-1..3). As in the C, a batch is one fixed buffer per
stream (a first sample and at most max_count records) and all arithmetic is on ints.
"""

from __future__ import annotations

from protocol.messages import (
    EncoderBatch,
    EncoderSample,
    EncoderStep,
    HeadBatch,
    HeadSample,
    HeadStep,
    RangeBatch,
    RangeSample,
    RangeStep,
)
from protocol.schema import SCHEMA

Sample = EncoderSample | RangeSample | HeadSample
Batch = EncoderBatch | RangeBatch | HeadBatch
Step = EncoderStep | RangeStep | HeadStep

_U32 = 0xFFFF_FFFF
_I16_LO, _I16_HI = -0x8000, 0x7FFF
_DT_HI = 0xFFFF


def _fits(*steps: int) -> bool:
    """Whether every step fits a record's i16."""
    return all(_I16_LO <= s <= _I16_HI for s in steps)


def _dt(sample: Sample, previous: Sample) -> int | None:
    """Time step in µs (mod 2³²), None when it does not fit the record's 1..65535."""
    dt = (sample.mcu_time_us - previous.mcu_time_us) & _U32
    return dt if 1 <= dt <= _DT_HI else None


def step_between(sample: Sample, previous: Sample) -> Step | None:
    """The record that turns `previous` into `sample`, or None when a step does not fit."""
    dt = _dt(sample, previous)
    if dt is None:
        return None
    if isinstance(sample, EncoderSample) and isinstance(previous, EncoderSample):
        enc = sample.encoder_count - previous.encoder_count
        steps = sample.step_count - previous.step_count
        vel = sample.velocity_counts_s - previous.velocity_counts_s
        return EncoderStep(dt, enc, steps, vel, sample.inputs) if _fits(enc, steps, vel) else None
    if isinstance(sample, RangeSample) and isinstance(previous, RangeSample):
        dist = sample.distance_um - previous.distance_um
        return RangeStep(dt, dist, sample.quality) if _fits(dist) else None
    if isinstance(sample, HeadSample) and isinstance(previous, HeadSample):
        pan, tilt = sample.pan_urad - previous.pan_urad, sample.tilt_urad - previous.tilt_urad
        return HeadStep(dt, pan, tilt) if _fits(pan, tilt) else None
    raise TypeError(f"cannot batch {type(sample).__name__} after {type(previous).__name__}")


def make_batch(first: Sample, steps: tuple[Step, ...]) -> Batch:
    """The batch message of a first sample and its records."""
    if isinstance(first, EncoderSample):
        enc_steps = tuple(s for s in steps if isinstance(s, EncoderStep))
        return EncoderBatch(
            first.mcu_time_us,
            first.encoder_count,
            first.step_count,
            first.velocity_counts_s,
            first.inputs,
            enc_steps,
        )
    if isinstance(first, RangeSample):
        range_steps = tuple(s for s in steps if isinstance(s, RangeStep))
        return RangeBatch(first.mcu_time_us, first.distance_um, first.quality, range_steps)
    head_steps = tuple(s for s in steps if isinstance(s, HeadStep))
    return HeadBatch(first.mcu_time_us, first.pan_urad, first.tilt_urad, head_steps)


_MAX_STEPS = {
    EncoderSample: SCHEMA.by_cls[EncoderBatch].records,
    RangeSample: SCHEMA.by_cls[RangeBatch].records,
    HeadSample: SCHEMA.by_cls[HeadBatch].records,
}


def max_steps(sample_type: type[Sample]) -> int:
    """Records a batch of this sample type holds (its first sample excluded)."""
    rec = _MAX_STEPS[sample_type]
    assert rec is not None
    return rec.max_count


class Batcher:
    """One stream's batch under construction: a first sample and at most max_count records."""

    __slots__ = ("_first", "_last", "_steps", "batches", "samples")

    def __init__(self) -> None:
        self._first: Sample | None = None
        self._last: Sample | None = None
        self._steps: list[Step] = []
        self.batches = 0  # batch frames made
        self.samples = 0  # samples put into them

    def __len__(self) -> int:
        """Samples waiting."""
        return 0 if self._first is None else 1 + len(self._steps)

    def clear(self) -> None:
        """Drop what is waiting (reset)."""
        self._first = self._last = None
        self._steps.clear()

    def add(self, sample: Sample) -> list[Batch]:
        """Take one sample; the batches now complete (0, 1 or 2), oldest first."""
        out: list[Batch] = []
        self.samples += 1
        if self._first is not None and self._last is not None:
            step = step_between(sample, self._last)
            if step is not None:
                self._steps.append(step)
                self._last = sample
                if len(self._steps) >= max_steps(type(sample)):
                    out.append(self._take())
                return out
            out.append(self._take())  # a step too large for its record: this one starts anew
        self._first = self._last = sample
        return out

    def due(self, now_us: int, age_us: int) -> Batch | None:
        """The batch, if its oldest sample has waited `age_us` (mod 2³² clock).

        Also once no later sample can join it: a time step longer than a record's 65 535 µs
        (a stream slower than ~15 Hz) starts a new batch, so there is nothing to wait for.
        """
        first, last = self._first, self._last
        if first is None or last is None:
            return None
        if (now_us - first.mcu_time_us) & _U32 < age_us and (
            now_us - last.mcu_time_us
        ) & _U32 < _DT_HI:
            return None
        return self._take()

    def flush(self) -> Batch | None:
        """Whatever is waiting, as a batch (stream switched off, new session, a mark)."""
        return None if self._first is None else self._take()

    def _take(self) -> Batch:
        """The waiting samples as one batch; the buffer is empty after."""
        assert self._first is not None
        batch = make_batch(self._first, tuple(self._steps))
        self.clear()
        self.batches += 1
        return batch
