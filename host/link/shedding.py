"""Telemetry shedding: slow the streams while the link loses the controller's frames.

A radio link carries a fixed number of bytes per second for both directions together. Streams
that ask for more fill the modules' buffers, which then lose whatever arrives: telemetry, and
the replies to commands just as often, so commands need retransmission after retransmission.
The controller's frames are numbered, so the host sees such losses as gaps in their seq
(`LinkStats.rx_lost`). On XBee the MAC retries every packet up to 3 times, so errors on the air
rarely show as a gap; a sustained gap rate means a buffer overflowing. The shedder then cuts
every stream to a fraction of the rate asked for (multiplicative decrease) and, once the link
has been clean for a while, gives a little back at a time (additive increase), as TCP does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class SheddingConfig:
    """When the streams are cut and given back."""

    window_s: float = 1.0  # losses are counted over windows this long
    loss_above: float = 0.05  # a window losing more than this fraction of frames is overload
    min_frames: int = 20  # a window with fewer frames (received + lost) says nothing
    cut: float = 0.5  # on overload the scale is multiplied by this
    floor: float = 0.125  # never below this fraction of the rates asked for
    step_up: float = 0.125  # added to the scale after a clean stretch, up to 1
    clean_s: float = 5.0  # how long the link must be clean before each step up

    def __post_init__(self) -> None:
        if self.window_s <= 0 or self.clean_s < self.window_s:
            raise ValueError("need window_s > 0 and clean_s ≥ window_s")
        if not 0 < self.loss_above < 1 or not 0 < self.cut < 1:
            raise ValueError("loss_above and cut must be fractions in (0, 1)")
        if not 0 < self.floor <= 1 or not 0 < self.step_up <= 1:
            raise ValueError("floor and step_up must be in (0, 1]")


class Shedder:
    """The fraction of the requested rates the link carries, from one window's counts at a time."""

    def __init__(self, config: SheddingConfig) -> None:
        self.config = config
        self.scale = 1.0
        self.cuts = 0  # overloaded windows that cut the rates
        self.steps_up = 0
        self._clean_windows = 0
        self._clean_needed = max(1, math.ceil(config.clean_s / config.window_s - 1e-9))

    def observe(self, received: int, lost: int) -> bool:
        """One window's frames received and lost; True if the scale changed."""
        cfg = self.config
        total = received + lost
        if total < cfg.min_frames:
            return False
        if lost > cfg.loss_above * total:
            self._clean_windows = 0
            if self.scale <= cfg.floor:
                return False
            self.scale = max(cfg.floor, self.scale * cfg.cut)
            self.cuts += 1
            return True
        if self.scale >= 1.0:
            return False
        self._clean_windows += 1
        if self._clean_windows < self._clean_needed:
            return False
        self._clean_windows = 0
        self.scale = min(1.0, self.scale + cfg.step_up)
        self.steps_up += 1
        return True

    def rate(self, requested_hz: int) -> int:
        """The rate to ask the controller for: scaled, but never switched off by shedding."""
        if requested_hz <= 0:
            return 0
        return max(1, round(requested_hz * self.scale))
