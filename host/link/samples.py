"""Decoded telemetry samples in host time and units, and the sink that receives them.

The live controller and the replay of recorded link bytes both turn ENCODER, HEAD, RANGE and
REF_MARK messages into sink calls; they do it here, so a replayed sample is the live one: the
controller clock mapped to host nanoseconds by the clock sync, counts scaled by the controller's
IDENTIFY, µm and µrad to mm and rad.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from host.link.clocksync import ClockSync
from host.link.common import UM_PER_MM
from host.link.snapshot import Identity
from protocol.messages import EncoderSample, HeadSample, RangeSample, RefMark

URAD_PER_RAD = 1_000_000.0

SampleMessage = EncoderSample | HeadSample | RangeSample | RefMark


class SampleSink(Protocol):
    """What the pose buffer implements to receive samples in host time."""

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """Track position sample."""

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """Head angle sample."""

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """Rangefinder sample."""

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """A reference mark passed; s_mm is the encoder position captured at its edge."""


@dataclass(frozen=True, slots=True)
class EncoderReading:
    """Track position from the controller's zero, mm and mm/s."""

    t_ns: int
    s_mm: float
    velocity_mm_s: float
    inputs: int

    def to(self, sink: SampleSink) -> None:
        """Hand it to a sink."""
        sink.on_encoder(self.t_ns, self.s_mm, self.velocity_mm_s, self.inputs)


@dataclass(frozen=True, slots=True)
class HeadReading:
    """Head angles, rad."""

    t_ns: int
    pan_rad: float
    tilt_rad: float

    def to(self, sink: SampleSink) -> None:
        """Hand it to a sink."""
        sink.on_head(self.t_ns, self.pan_rad, self.tilt_rad)


@dataclass(frozen=True, slots=True)
class RangeReading:
    """Rangefinder distance along the beam, mm."""

    t_ns: int
    distance_mm: float
    quality: int

    def to(self, sink: SampleSink) -> None:
        """Hand it to a sink."""
        sink.on_range(self.t_ns, self.distance_mm, self.quality)


@dataclass(frozen=True, slots=True)
class MarkReading:
    """Encoder position captured at a reference mark's edge, mm."""

    t_ns: int
    s_mm: float

    def to(self, sink: SampleSink) -> None:
        """Hand it to a sink."""
        sink.on_mark(self.t_ns, self.s_mm)


Reading = EncoderReading | HeadReading | RangeReading | MarkReading


def frame_arrived(
    clock: ClockSync, frame: object, samples: Sequence[SampleMessage], arrival_ns: int
) -> None:
    """A telemetry frame's newest stamp and arrival, for the clock's rate (host.link.skew).

    Frames of another message or sample count spend another time on the wire, so each pair is
    its own kind. A mark is left out: it goes when its edge comes, not when a frame fills.
    """
    if samples and not isinstance(frame, RefMark):
        clock.add_arrival((type(frame).__name__, len(samples)), samples[-1].mcu_time_us, arrival_ns)


def reading(msg: SampleMessage, clock: ClockSync, identity: Identity | None) -> Reading | None:
    """The sample in host time and units; None until an IDENTIFY and a clock probe allow it."""
    if not clock.ready or identity is None:
        return None
    t_ns = clock.mcu_to_host_ns(msg.mcu_time_us)
    k = identity.mm_per_count
    if isinstance(msg, EncoderSample):
        return EncoderReading(t_ns, msg.encoder_count * k, msg.velocity_counts_s * k, msg.inputs)
    if isinstance(msg, HeadSample):
        return HeadReading(t_ns, msg.pan_urad / URAD_PER_RAD, msg.tilt_urad / URAD_PER_RAD)
    if isinstance(msg, RefMark):
        return MarkReading(t_ns, msg.encoder_count * k)
    return RangeReading(t_ns, msg.distance_um / UM_PER_MM, msg.quality)
