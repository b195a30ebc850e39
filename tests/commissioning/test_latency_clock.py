"""The latency run's clock-sync σ: the link's estimator's own, measured while it runs."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from host.commissioning.ops import _clock_sigma_ms
from host.link.clocksync import ClockSync

US = 1_000


def fed_clock(round_trip_ns: list[int]) -> ClockSync:
    """A clock fed 10 Hz probes with these round trips (symmetric legs, no residence)."""
    clock = ClockSync()
    for k, rtt in enumerate(round_trip_ns):
        t0 = 1_000_000_000 + k * 100_000_000
        mcu_us = (t0 + rtt // 2) // US
        clock.add_probe(t0, mcu_us, t0 + rtt, mcu_us)
    return clock


def test_no_session_or_no_fit_gives_none() -> None:
    """A controller without a link, or a clock without a probe yet: nothing measured."""
    assert _clock_sigma_ms(object()) is None
    assert _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=ClockSync()))) is None


def test_the_estimators_uncertainty_in_ms() -> None:
    """The σ is the estimator's own uncertainty, converted to milliseconds."""
    clock = fed_clock([5_000_000 + (k % 7) * 300_000 for k in range(60)])
    got = _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=clock)))
    assert got == pytest.approx(clock.uncertainty_ns() / 1e6)
    assert got is not None
    assert got > 0.0


def test_slower_round_trips_give_a_larger_sigma() -> None:
    """A loaded link (round trips spread by milliseconds) is trusted less than a quiet one."""
    quiet = fed_clock([5_000_000 + (k % 7) * 20_000 for k in range(60)])
    loaded = fed_clock([5_000_000 + (k % 7) * 1_500_000 for k in range(60)])
    q = _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=quiet)))
    lo = _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=loaded)))
    assert q is not None
    assert lo is not None
    assert lo > q
