"""The clock probes: fast until the fit converges, slow while it holds, fast on a jump or reset."""

from __future__ import annotations

import random

from host.link.clocksync import ClockSync
from host.link.probe_rate import MIN_PROBES_TO_SLOW, ProbeRate

DRIFT = 1.0 + 20e-6  # host ns per controller µs, over 1000: a 20 ppm crystal


class Link:
    """A controller clock 20 ppm fast behind a link of 5 ms ± jitter each way."""

    def __init__(self, jitter_ns: int = 200_000, seed: int = 1) -> None:
        self.rng = random.Random(seed)
        self.jitter_ns = jitter_ns
        self.offset_us = 123_456
        self.t_ns = 10**12

    def mcu_at(self, host_ns: int) -> int:
        """The controller clock (32-bit µs) at a host time."""
        return (self.offset_us + round(host_ns / 1000 * DRIFT)) & 0xFFFF_FFFF

    def probe(self, clock: ClockSync, interval_s: float, rate: ProbeRate | None = None) -> None:
        """One probe after `interval_s` (its reply checked by `rate`, as the session does)."""
        self.t_ns += round(interval_s * 1e9)
        out = 5_000_000 + self.rng.randrange(self.jitter_ns)
        back = 5_000_000 + self.rng.randrange(self.jitter_ns)
        stamp = self.mcu_at(self.t_ns + out)
        if rate is not None:
            rate.check_reply(clock, self.t_ns, stamp, self.t_ns + out + back)
        clock.add_probe(self.t_ns, stamp, self.t_ns + out + back, stamp)


def test_fast_until_converged_then_slow() -> None:
    clock, link, rate = ClockSync(), Link(), ProbeRate(0.1, 1.0)
    intervals = []
    for _ in range(300):
        interval = rate.interval_s(clock, link.t_ns)
        intervals.append(interval)
        link.probe(clock, interval)
    assert intervals[: MIN_PROBES_TO_SLOW // 2] == [0.1] * (MIN_PROBES_TO_SLOW // 2)
    assert intervals[-50:] == [1.0] * 50
    assert rate.switches == 1  # no flapping
    # Slow probes still hold the mapping to the target.
    err_ns = clock.mcu_to_host_ns(link.mcu_at(link.t_ns)) - link.t_ns
    assert abs(err_ns) < 200_000


def test_fast_again_when_the_clock_jumps_and_after_a_reset() -> None:
    clock, link, rate = ClockSync(), Link(), ProbeRate(0.1, 1.0)
    for _ in range(200):
        link.probe(clock, rate.interval_s(clock, link.t_ns))
    assert rate.slow
    link.offset_us += 30_000  # a clock step: the mapping is 30 ms off, beyond a round trip
    link.probe(clock, rate.interval_s(clock, link.t_ns), rate)
    assert not rate.slow
    assert rate.violations == 1
    for _ in range(400):
        link.probe(clock, rate.interval_s(clock, link.t_ns))
    assert rate.slow  # the fit restarted on the step and converged again
    rate.reset()
    assert not rate.slow
    assert rate.interval_s(ClockSync(), link.t_ns) == 0.1


def test_a_slow_interval_not_above_the_fast_one_keeps_the_rate() -> None:
    clock, link, rate = ClockSync(), Link(), ProbeRate(0.1, 0.1)
    for _ in range(200):
        assert rate.interval_s(clock, link.t_ns) == 0.1
        link.probe(clock, 0.1)
