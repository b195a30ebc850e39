"""Pose buffers fed by the controller link: encoder-only (the paper) and drift-corrected.

Both are sample sinks of `host.link.Controller`. The encoder-only feed maps the controller's
position (mm from home) onto the track by the surveyed home position; the fused feed also
runs the chain filter on absolute reference marks and pushes the corrected arc length into its
own buffer. Marks arrive as REF_MARK messages carrying the encoder count captured at the
mark's edge, so a reference is as precise as one encoder count.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from host.fusion.chain_filter import ChainFilter
from host.registration.pose_buffer import AngleBuffer, SampleBuffer

ENCODER_CAPACITY = 8192  # 16 s at 500 Hz
HEAD_CAPACITY = 2048


@dataclass
class TrackFeed:
    """Encoder and head samples into pose buffers, raw and fused."""

    home_s_mm: float = 0.0  # track arc length of the controller's zero (installation survey)
    marks_mm: tuple[float, ...] = ()
    chain: ChainFilter = field(default_factory=ChainFilter)
    raw: SampleBuffer = field(default_factory=lambda: SampleBuffer(1, ENCODER_CAPACITY))
    fused: SampleBuffer = field(default_factory=lambda: SampleBuffer(1, ENCODER_CAPACITY))
    head: AngleBuffer = field(default_factory=lambda: AngleBuffer(2, HEAD_CAPACITY))
    last_enc_mm: float | None = None
    marks_seen: int = 0

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """One encoder sample (controller mm from home) → both buffers."""
        enc = self.home_s_mm + s_mm
        self.last_enc_mm = enc
        self.chain.predict(enc)
        self.raw.push(t_host_ns, [enc])
        self.fused.push(t_host_ns, [self.chain.estimate(enc)[0]])

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """One head sample."""
        self.head.push(t_host_ns, [pan_rad, tilt_rad])

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """Rangefinder samples are not used by the registration loop."""

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """A reference mark's captured encoder position: associate it, update the filter."""
        enc_mm = self.home_s_mm + s_mm
        mark = self.chain.associate(enc_mm, self.marks_mm)
        if mark is not None:
            self.chain.reference(enc_mm, mark)
            self.marks_seen += 1

    def reset(self, home_s_mm: float) -> None:
        """After (re)homing: new survey offset, fresh filter and buffers."""
        self.home_s_mm = home_s_mm
        self.chain = ChainFilter(self.chain.config)
        self.raw.clear()
        self.fused.clear()
        self.last_enc_mm = None
