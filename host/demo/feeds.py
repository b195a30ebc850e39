"""The demo's two registrations side by side, both on the daemon's own `PoseFeed`.

The encoder-only feed is the paper's method; the corrected feed also runs the chain filter on
the absolute references: REF_MARK captures (the encoder count at each mark's edge) and
rangefinder readings of the hall's surveyed walls. One sink fans the controller's samples out
to both, so they see exactly the same data.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from host.fusion.chain_filter import ChainFilter, ChainFilterConfig
from host.fusion.range_fix import RangeFixer
from host.registration.pose_buffer import AngleBuffer, SampleBuffer
from host.registration.track_feed import PoseFeed
from host.service.wiring import ENCODER_HORIZON_NS, HEAD_HORIZON_NS, MAX_GAP_NS

ENCODER_CAPACITY = 8192  # 16 s at 500 Hz
HEAD_CAPACITY = 2048


def _feed(
    marks_mm: tuple[float, ...],
    pitch_mm: float,
    ranger: RangeFixer | None = None,
    config: ChainFilterConfig | None = None,
) -> PoseFeed:
    """A PoseFeed with buffers sized for the demo's longest lookups, horizons as the daemon's."""
    return PoseFeed(
        SampleBuffer(1, ENCODER_CAPACITY, ENCODER_HORIZON_NS, MAX_GAP_NS),
        AngleBuffer(2, HEAD_CAPACITY, HEAD_HORIZON_NS, MAX_GAP_NS),
        marks_mm=marks_mm,
        pitch_mm=lambda: pitch_mm,
        ranger=ranger,
        chain=None if config is None else ChainFilter(config),
    )


@dataclass
class TrackFeed:
    """Encoder-only and drift-corrected pose buffers fed from one controller."""

    marks_mm: tuple[float, ...] = ()
    pitch_mm: float = 12.7
    ranger: RangeFixer | None = None
    config: ChainFilterConfig | None = None  # the filter's (the rig file's marks σ)
    encoder_only: PoseFeed = field(init=False)
    corrected: PoseFeed = field(init=False)

    def __post_init__(self) -> None:
        self.encoder_only = _feed((), self.pitch_mm)
        self.corrected = _feed(self.marks_mm, self.pitch_mm, self.ranger, self.config)

    @property
    def raw(self) -> SampleBuffer:
        """The paper's registration: encoder arc length only."""
        return self.encoder_only.encoder

    @property
    def fused(self) -> SampleBuffer:
        """Arc length corrected by the chain filter."""
        return self.corrected.encoder

    @property
    def head(self) -> AngleBuffer:
        """Head angles (the same samples reach both feeds)."""
        return self.encoder_only.head

    @property
    def home_s_mm(self) -> float:
        """Track arc length of the controller's zero (the installation survey)."""
        return self.encoder_only.home_s_mm

    @property
    def last_enc_mm(self) -> float | None:
        """Latest encoder-only track position."""
        return self.encoder_only.raw_s_mm

    @property
    def chain(self) -> ChainFilter:
        """The corrected feed's filter (the demo always has marks)."""
        assert self.corrected.chain is not None
        return self.corrected.chain

    @property
    def marks_seen(self) -> int:
        """REF_MARK events received while homed."""
        return self.corrected.marks_seen - self.corrected.marks_unhomed

    def set_home(self, home_s_mm: float, sigma_mm: float | None = None) -> None:
        """After (re)homing: the surveyed home (σ: how well it is known now, if better than
        the homing's repeatability the filter assumes), fresh buffers and filter."""
        self.encoder_only.rehome(home_s_mm)
        chain = self.corrected.chain
        if chain is not None:
            config = self.config or chain.config
            if sigma_mm is not None:
                config = dataclasses.replace(config, offset_sigma0_mm=sigma_mm)
            self.corrected.chain = ChainFilter(
                dataclasses.replace(config, chain_pitch_mm=chain.config.chain_pitch_mm)
            )
        self.corrected.rehome(home_s_mm)

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """To both feeds."""
        self.encoder_only.on_encoder(t_host_ns, s_mm, velocity_mm_s, inputs)
        self.corrected.on_encoder(t_host_ns, s_mm, velocity_mm_s, inputs)

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """To both feeds."""
        self.encoder_only.on_head(t_host_ns, pan_rad, tilt_rad)
        self.corrected.on_head(t_host_ns, pan_rad, tilt_rad)

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """Only the corrected feed uses the rangefinder."""
        self.corrected.on_range(t_host_ns, distance_mm, quality)

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """Only the corrected feed uses marks."""
        self.corrected.on_mark(t_host_ns, s_mm)
