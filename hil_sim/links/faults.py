"""Fault injection shared by every emulated link: loss, bursts, bit errors, latency, jitter.

One `FaultConfig` describes what to inject and one `FaultInjector` applies it to each unit the
link moves (a UART chunk, an XBee RF packet, a CAN frame). The RNG is seeded so a run repeats,
and every injected fault is counted so tests compare the link's statistics with the truth.
Disconnects are an action of the link itself (close a pty, bus-off); the link counts them here.

Bursts follow the Gilbert–Elliott model: a good state with loss `drop_rate` and a bad state that
loses everything; the chain enters the bad state with `burst_rate` per unit and stays for
`burst_length_mean` units on average.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass, field


@dataclass(frozen=True)
class FaultConfig:
    """What a link injects; the defaults inject nothing."""

    drop_rate: float = 0.0  # probability a unit is lost in the good state
    bit_error_rate: float = 0.0  # probability each bit of a delivered unit flips
    burst_rate: float = 0.0  # probability per unit of entering a loss burst
    burst_length_mean: float = 1.0  # mean units lost per burst
    latency_s: float = 0.0  # fixed one-way delay added to every unit
    jitter_s: float = 0.0  # uniform extra delay in [0, jitter_s]
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("drop_rate", "bit_error_rate", "burst_rate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"faults.{name}={value} outside [0, 1]")
        for name in ("latency_s", "jitter_s"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"faults.{name} must not be negative")
        if self.burst_length_mean < 1.0:
            raise ValueError("faults.burst_length_mean must be at least 1 unit")

    @property
    def inert(self) -> bool:
        """True when nothing would ever be injected."""
        return self == FaultConfig(seed=self.seed)


@dataclass
class FaultCounters:
    """Everything injected so far."""

    units: int = 0
    dropped: int = 0
    burst_dropped: int = 0
    bursts: int = 0
    corrupted: int = 0
    bits_flipped: int = 0
    delayed: int = 0
    disconnects: int = 0

    @property
    def lost(self) -> int:
        """Units lost for any reason."""
        return self.dropped + self.burst_dropped


@dataclass
class FaultInjector:
    """Applies a `FaultConfig` unit by unit with its own seeded RNG."""

    config: FaultConfig = field(default_factory=FaultConfig)
    counters: FaultCounters = field(default_factory=FaultCounters)
    _rng: random.Random = field(init=False)
    _in_burst: bool = False

    def __post_init__(self) -> None:
        self._rng = random.Random(self.config.seed)

    def transmit(self, data: bytes) -> bytes | None:
        """One unit through the faulty medium: None if lost, else the bytes (maybe flipped)."""
        self.counters.units += 1
        if self._lose():
            return None
        if self.config.bit_error_rate > 0.0:
            data = self._flip_bits(data)
        return data

    def delay_s(self) -> float:
        """One-way delay for the next unit: latency plus uniform jitter."""
        cfg = self.config
        delay = cfg.latency_s + (self._rng.uniform(0.0, cfg.jitter_s) if cfg.jitter_s else 0.0)
        if delay > 0.0:
            self.counters.delayed += 1
        return delay

    def note_disconnect(self) -> None:
        """The link was cut on purpose."""
        self.counters.disconnects += 1

    def _lose(self) -> bool:
        """Advance the Gilbert–Elliott chain and decide whether this unit is lost."""
        cfg = self.config
        if self._in_burst:
            # Geometric burst length with the configured mean.
            if self._rng.random() < 1.0 / cfg.burst_length_mean:
                self._in_burst = False
            else:
                self.counters.burst_dropped += 1
                return True
        if cfg.burst_rate and self._rng.random() < cfg.burst_rate:
            self._in_burst = True
            self.counters.bursts += 1
            self.counters.burst_dropped += 1
            return True
        if cfg.drop_rate and self._rng.random() < cfg.drop_rate:
            self.counters.dropped += 1
            return True
        return False

    def _flip_bits(self, data: bytes) -> bytes:
        """Flip each bit with probability BER, drawing the gaps between errors geometrically."""
        n_bits = len(data) * 8
        ber = self.config.bit_error_rate
        pos = self._next_gap(ber)
        if pos >= n_bits:
            return data
        out = bytearray(data)
        while pos < n_bits:
            out[pos // 8] ^= 1 << (pos % 8)
            self.counters.bits_flipped += 1
            pos += 1 + self._next_gap(ber)
        self.counters.corrupted += 1
        return bytes(out)

    def _next_gap(self, ber: float) -> int:
        """Good bits before the next error."""
        if ber >= 1.0:
            return 0
        u = 1.0 - self._rng.random()  # (0, 1]: log is finite
        return int(math.log(u) / math.log1p(-ber))
