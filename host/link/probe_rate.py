"""How often to probe the controller clock: fast until the fit converges, slow while it holds.

Each CLOCK_SYNC probe and its reply cost air (over XBee 2 × 41 bytes, 2 % of the air per Hz), so
the session spends them only as the estimator needs them. It probes at the fast interval after
a start or a reset (a new fit), and drops to the slow interval once the fit has enough probes
and its one-sigma error, extrapolated to the next probe, stays well inside the target. When the
error grows past the target's half (jitter rose, a clock step restarted the fit) it goes fast
again. Between the two thresholds it keeps what it was doing, so it does not flap.
"""

from __future__ import annotations

from dataclasses import dataclass

from host.link.clocksync import ClockSync

ERROR_TARGET_NS = 200_000  # what the clock mapping must keep to, over the radio's jitter too
SLOW_BELOW_FRACTION = 0.25  # slow down once the extrapolated error is below this × target
FAST_ABOVE_FRACTION = 0.5  # speed up again above this × target
MIN_PROBES_TO_SLOW = 40  # probes the fit must have used before it may slow down


@dataclass
class ProbeRate:
    """The interval to the next clock probe, from the estimator's own error estimate."""

    fast_s: float = 0.1
    slow_s: float = 1.0
    target_ns: float = ERROR_TARGET_NS
    slow: bool = False
    switches: int = 0  # changes between fast and slow, for the statistics

    def interval_s(self, clock: ClockSync, now_mcu_us: int | None = None) -> float:
        """Seconds until the next probe; `now_mcu_us` is the controller time now, if known."""
        if self.slow_s <= self.fast_s:
            return self.fast_s
        error = self.error_ns(clock, now_mcu_us)
        if error is None or clock.probes_used < MIN_PROBES_TO_SLOW:
            error = float("inf")  # a fit too young to trust: probe fast
        if error > FAST_ABOVE_FRACTION * self.target_ns:
            self._set(slow=False)
        elif error < SLOW_BELOW_FRACTION * self.target_ns:
            self._set(slow=True)
        return self.slow_s if self.slow else self.fast_s

    def error_ns(self, clock: ClockSync, now_mcu_us: int | None = None) -> float | None:
        """The fit's one-sigma error a slow interval after now; None before the first probe."""
        if not clock.ready:
            return None
        if now_mcu_us is None:
            return clock.uncertainty_ns()
        ahead_us = round(self.slow_s * 1e6)
        return clock.uncertainty_ns((now_mcu_us + ahead_us) & 0xFFFF_FFFF)

    def reset(self) -> None:
        """A new fit (controller reset): probe fast again."""
        self._set(slow=False)

    def _set(self, slow: bool) -> None:
        """Switch, counting the changes."""
        if slow != self.slow:
            self.slow = slow
            self.switches += 1
