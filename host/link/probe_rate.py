"""How often to probe the controller clock: fast until the fit converges, slow while it holds.

Each CLOCK_SYNC probe and its reply cost air (over XBee 2 × 41 bytes, ~2 % of the air per Hz),
so the session spends them only as the estimator needs them. It probes at the fast interval
after a start or a reset (a new fit), and drops to the slow interval once the fit has enough
probes and has stopped moving: the error estimate is how far each update moved the mapping at
a time just ahead (the fit's own one-sigma figure is far too pessimistic on a jittery radio to
be compared with a target), smoothed over the last updates. While that stays well inside the
target it probes slowly. It goes fast again when the smoothed figure passes half the target,
when one update moves the mapping by more than the target, when successive probes are
rejected as outliers, or when a reply's stamp maps outside its own round trip (a clock step).
Between the two thresholds it keeps what it was doing, so it does not flap.
"""

from __future__ import annotations

from dataclasses import dataclass

from host.link.clocksync import ClockSync

ERROR_TARGET_NS = 200_000  # what the clock mapping must keep to, over the radio's jitter too
SLOW_BELOW_FRACTION = 0.25  # slow down once the smoothed update is below this × target
FAST_ABOVE_FRACTION = 0.5  # speed up again above this × target
MIN_PROBES_TO_SLOW = 24  # probes the fit must have used before it may slow down
SMOOTHING = 0.2  # weight of the newest update in the smoothed error
OUTLIER_STREAK = 2  # this many probes in a row the fit rejects as outliers: probe fast again


@dataclass
class ProbeRate:
    """The interval to the next clock probe, from how much the fit still moves."""

    fast_s: float = 0.1
    slow_s: float = 1.0
    target_ns: float = ERROR_TARGET_NS
    slow: bool = False
    switches: int = 0  # changes between fast and slow, for the statistics
    violations: int = 0  # replies the mapping put outside their own round trip
    error_ns: float | None = None  # smoothed movement of the mapping per update
    _probes: int = 0
    _outliers: int = 0
    _outlier_streak: int = 0  # successive observations that each brought new outliers
    _check: tuple[int, int] | None = None  # (extended MCU time ahead, its host ns) as last fitted

    def interval_s(self, clock: ClockSync, now_ns: int) -> float:
        """Seconds until the next probe; `now_ns`: host monotonic time now."""
        if self.slow_s <= self.fast_s:
            return self.fast_s
        self._observe(clock, now_ns)
        error = self.error_ns
        if error is None or clock.probes_used < MIN_PROBES_TO_SLOW:
            error = float("inf")  # a fit too young to trust: probe fast
        if error > FAST_ABOVE_FRACTION * self.target_ns:
            self._set(slow=False)
        elif error < SLOW_BELOW_FRACTION * self.target_ns:
            self._set(slow=True)
        return self.slow_s if self.slow else self.fast_s

    def check_reply(self, clock: ClockSync, t0_ns: int, mcu_us: int, t1_ns: int) -> None:
        """Every reply, kept or filtered by the fit: its stamp was read between send and receipt.

        A mapping that puts it outside [t0, t1] by more than the target is wrong by at least
        that much (a clock step the fit has not seen yet): probe fast at once.
        """
        if not clock.ready:
            return
        at_ns = clock.mcu_to_host_ns(mcu_us)
        if at_ns < t0_ns - self.target_ns or at_ns > t1_ns + self.target_ns:
            self.violations += 1
            self._set(slow=False)

    def reset(self) -> None:
        """A new fit (controller reset): probe fast again and forget the error."""
        self._set(slow=False)
        self.error_ns = None
        self._probes = 0
        self._check = None

    def _observe(self, clock: ClockSync, now_ns: int) -> None:
        """After new probes: how far they moved the mapping at the time checked last."""
        if not clock.ready:
            return
        fresh_outliers = clock.outliers != self._outliers
        self._outliers = clock.outliers
        self._outlier_streak = self._outlier_streak + 1 if fresh_outliers else 0
        if self._outlier_streak >= OUTLIER_STREAK:
            self._set(slow=False)  # the probes disagree with the fit: the clock may have jumped
        if clock.probes_used != self._probes and self._check is not None:
            moved = abs(clock.ext_to_host_ns(self._check[0]) - self._check[1])
            prev = self.error_ns
            self.error_ns = moved if prev is None else prev + SMOOTHING * (moved - prev)
            if moved > self.target_ns:
                self._set(slow=False)  # one large move is enough to look closer
        self._probes = clock.probes_used
        ahead = clock.host_to_mcu(now_ns + round(self.slow_s * 1e9))
        self._check = (ahead, clock.ext_to_host_ns(ahead))

    def _set(self, slow: bool) -> None:
        """Switch, counting the changes."""
        if slow != self.slow:
            self.slow = slow
            self.switches += 1
