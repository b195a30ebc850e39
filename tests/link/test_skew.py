"""The controller clock's rate from the telemetry's one-way delays, alone and in the clock sync."""

from __future__ import annotations

import random
from types import SimpleNamespace
from typing import Any

import pytest

from host.config import loads_config
from host.link.clocksync import WRAP_US, ClockSync
from host.link.skew import MIN_BINS, SkewEnvelope
from host.recording.link_replay import LinkReplay
from host.service.wiring import CLOCK_ASYMMETRY_SIGMA_US, clock_stats, controller_factory
from host.transport.memory import MemoryTransport
from protocol import Packet, encode_frame
from protocol.messages import EncoderBatch, EncoderSample, EncoderStep, RefMark

DRIFT_PPM = 20.0
NS_PER_S = 1_000_000_000
# Three kinds of frame with their own least delay, as encoder batches, range batches and head
# samples have over the radio: (kind, frames a second, floor ns).
KINDS = (("enc", 25, 9_000_000), ("range", 12, 6_000_000), ("head", 10, 4_500_000))


def mcu_at(host_ns: float, drift_ppm: float = DRIFT_PPM) -> int:
    """The controller's clock (extended µs) at a host time: 20 ppm fast, 123 s ahead."""
    return 123_000_000 + int(host_ns * (1 + drift_ppm * 1e-6) / 1000)


def feed(
    env: SkewEnvelope | ClockSync,
    rng: random.Random,
    start_s: float,
    seconds: float,
    busy_from_s: float | None = None,
    step_from_s: float | None = None,
) -> None:
    """Telemetry for `seconds`: every frame waits a random queue above its kind's floor, from
    nothing (a free link) to ~20 ms; from `busy_from_s` on, 3 s in which every frame waited;
    from `step_from_s` on, every floor 2 ms higher."""
    frames = []
    for kind, hz, floor_ns in KINDS:
        n = int(seconds * hz)
        for i in range(n):
            sent_ns = (start_s + i / hz + rng.uniform(0, 0.002)) * NS_PER_S
            queue_ns = 0.0 if rng.random() < 0.1 else rng.expovariate(1 / 4e6)
            if busy_from_s is not None and busy_from_s <= sent_ns / NS_PER_S < busy_from_s + 3:
                queue_ns += 20e6
            if step_from_s is not None and sent_ns / NS_PER_S >= step_from_s:
                queue_ns += 2e6
            frames.append((sent_ns + floor_ns + queue_ns + rng.uniform(0, 30e3), kind, sent_ns))
    for arrival_ns, kind, sent_ns in sorted(frames):
        if isinstance(env, ClockSync):
            env.add_arrival(kind, mcu_at(sent_ns) % WRAP_US, int(arrival_ns))
        else:
            env.add(kind, mcu_at(sent_ns), int(arrival_ns))


def drift_ppm_of(ns_per_tick: float) -> float:
    """The controller clock's rate error from host ns per tick."""
    return (1000.0 / ns_per_tick - 1.0) * 1e6


def test_envelope_recovers_the_rate_within_its_reported_sigma() -> None:
    for seed in range(5):
        env = SkewEnvelope(1000.0)
        feed(env, random.Random(seed), 0.0, 90.0)
        est = env.estimate()
        assert est is not None
        sigma_ppm = est.variance**0.5 / 1000.0 * 1e6
        error_ppm = drift_ppm_of(est.ns_per_tick) - DRIFT_PPM
        assert abs(error_ppm) < 3 * sigma_ppm, (seed, error_ppm, sigma_ppm)
        assert abs(error_ppm) < 1.0
        assert sigma_ppm < 1.0
        assert est.bins >= 3 * 70  # some high minima of the skewed floor are dropped too


def test_seconds_in_which_every_frame_waited_are_left_out() -> None:
    env = SkewEnvelope(1000.0)
    feed(env, random.Random(7), 0.0, 60.0, busy_from_s=50.0)  # late in the window: a lever
    est = env.estimate()
    assert est is not None
    assert est.rejected >= 3 * 2
    assert abs(drift_ppm_of(est.ns_per_tick) - DRIFT_PPM) < 1.0


def test_nothing_before_enough_seconds_and_stale_stamps_add_nothing() -> None:
    env = SkewEnvelope(1000.0)
    feed(env, random.Random(3), 0.0, MIN_BINS - 0.5)  # the first second is partial
    assert env.estimate() is None
    feed(env, random.Random(4), MIN_BINS - 0.5, 30.0)
    before = env.estimate()
    assert before is not None
    # A frame stamped 20 s ago arriving now (a stale batch) changes nothing.
    env.add("range", mcu_at(10 * NS_PER_S), int(38 * NS_PER_S))
    assert env.estimate() == before


def test_kinds_beyond_the_cap_forget_the_stalest() -> None:
    env = SkewEnvelope(1000.0)
    for kind in range(40):
        env.add(kind, mcu_at(kind * 1e6), int(kind * 1e6))
    assert len(env._kinds) <= 16
    assert 39 in env._kinds
    assert 0 not in env._kinds


def biased_probe(sync: ClockSync, rng: random.Random, i: int, step_us: int = 0) -> None:
    """Probe `i` (1 Hz) over a half-duplex radio whose traffic changes every 15 s and with it
    how the least round trip splits between the legs (±1 ms): a bias no probe can see."""
    t0 = i * NS_PER_S + rng.uniform(0, 1e6)
    split = random.Random(i // 15).uniform(-1e6, 1e6)
    out = 5e6 + split + rng.expovariate(1 / 0.3e6)
    back = 5e6 - split + rng.expovariate(1 / 0.3e6)
    rx = mcu_at(t0 + out) + step_us
    sync.add_probe(int(t0), rx % WRAP_US, int(t0 + out + back), rx % WRAP_US)


def paired_syncs(seed: int, seconds: int = 60) -> tuple[ClockSync, ClockSync]:
    """The same biased probes to two clock syncs, one of them fed the telemetry as well."""
    with_telemetry, probes_only = ClockSync(), ClockSync()
    rng_with, rng_without, tele = random.Random(seed), random.Random(seed), random.Random(~seed)
    for second in range(seconds):
        feed(with_telemetry, tele, float(second), 1.0)
        biased_probe(with_telemetry, rng_with, second)
        biased_probe(probes_only, rng_without, second)
    return with_telemetry, probes_only


def test_the_clock_sync_takes_its_rate_from_telemetry_over_biased_probes() -> None:
    with_telemetry, probes_only = paired_syncs(11)
    assert with_telemetry.skew() is not None
    assert probes_only.skew() is None
    err_with = abs(with_telemetry.estimate().drift_ppm - DRIFT_PPM)
    err_without = abs(probes_only.estimate().drift_ppm - DRIFT_PPM)
    assert err_with < 1.5, err_with
    assert err_without > 3 * err_with, (err_without, err_with)


def test_reset_and_a_clock_step_forget_the_envelope() -> None:
    sync = ClockSync()
    rng, tele = random.Random(5), random.Random(6)
    for second in range(20):
        feed(sync, tele, float(second), 1.0)
        biased_probe(sync, rng, second)
    assert sync.skew() is not None
    sync.reset()
    assert sync.skew() is None
    for second in range(20, 40):
        feed(sync, tele, float(second), 1.0)
        biased_probe(sync, rng, second)
    assert sync.skew() is not None
    for second in range(40, 140):  # the controller's clock jumps 10 s: the fit starts over
        biased_probe(sync, rng, second, step_us=10_000_000)
    assert sync.skew() is None


def test_link_stats_show_the_telemetry_drift_beside_the_fit() -> None:
    sync = ClockSync()
    ctrl: Any = SimpleNamespace(session=SimpleNamespace(clock=sync))
    assert clock_stats(ctrl)["clock_telemetry_drift_ppm"] is None
    rng, tele = random.Random(5), random.Random(6)
    for second in range(40):
        feed(sync, tele, float(second), 1.0)
        biased_probe(sync, rng, second)
    stats = clock_stats(ctrl)
    assert abs(stats["clock_telemetry_drift_ppm"] - DRIFT_PPM) < 2.0
    assert abs(stats["clock_drift_ppm"] - stats["clock_telemetry_drift_ppm"]) < 2.0


def test_the_links_asymmetry_sigma_is_part_of_the_clocks_uncertainty() -> None:
    plain, radio = ClockSync(), ClockSync(asymmetry_sigma_ns=500_000.0)
    rng_a, rng_b = random.Random(8), random.Random(8)
    for second in range(30):
        biased_probe(plain, rng_a, second)
        biased_probe(radio, rng_b, second)
    assert radio.mcu_to_host_ns(mcu_at(29e9) % WRAP_US) == plain.mcu_to_host_ns(
        mcu_at(29e9) % WRAP_US
    )  # the mapping is the same: only what it is known to differs
    fit_ns = plain.uncertainty_ns()
    assert radio.uncertainty_ns() == pytest.approx((fit_ns**2 + 500_000.0**2) ** 0.5)
    with pytest.raises(ValueError, match="asymmetry_sigma_ns"):
        ClockSync(asymmetry_sigma_ns=-1.0)


def test_the_daemon_gives_the_radio_its_asymmetry_sigma() -> None:
    for kind, sigma_us in (("xbee", CLOCK_ASYMMETRY_SIGMA_US["xbee"]), ("serial", 0.0)):
        config = loads_config(f'[link]\nkind = "{kind}"\n')
        ctrl = controller_factory(config, lambda *_: None, MemoryTransport())
        assert ctrl.session.config.clock_asymmetry_sigma_us == sigma_us
        assert ctrl.session.clock.asymmetry_sigma_ns == sigma_us * 1000.0
    assert CLOCK_ASYMMETRY_SIGMA_US["xbee"] > 0.0  # the radio's is not left out


def feed_at(
    env: SkewEnvelope, rng: random.Random, start_s: float, seconds: float, clock: Any
) -> None:
    """As `feed`, on a controller clock given as host ns → extended ticks."""
    frames = []
    for kind, hz, floor_ns in KINDS:
        for i in range(int(seconds * hz)):
            sent_ns = (start_s + i / hz + rng.uniform(0, 0.002)) * NS_PER_S
            queue_ns = 0.0 if rng.random() < 0.1 else rng.expovariate(1 / 4e6)
            frames.append((sent_ns + floor_ns + queue_ns, kind, sent_ns))
    for arrival_ns, kind, sent_ns in sorted(frames):
        env.add(kind, clock(sent_ns), int(arrival_ns))


def test_the_estimate_follows_a_rate_that_changes_after_the_window_filled() -> None:
    env, rng = SkewEnvelope(1000.0), random.Random(21)
    feed_at(env, rng, 0.0, 150.0, mcu_at)
    first = env.estimate()
    assert first is not None
    assert abs(drift_ppm_of(first.ns_per_tick) - DRIFT_PPM) < 1.0

    # From 150 s the crystal runs 10 ppm faster (warmed up): continuous at the change.
    def warmer(host_ns: float) -> int:
        return mcu_at(150e9) + int((host_ns - 150e9) * (1 + 30e-6) / 1000)

    feed_at(env, rng, 150.0, 150.0, warmer)
    est = env.estimate()
    assert est is not None
    assert abs(drift_ppm_of(est.ns_per_tick) - 30.0) < 1.0


def test_minima_from_before_a_long_silence_are_left_out() -> None:
    env, rng = SkewEnvelope(1000.0), random.Random(22)
    feed_at(env, rng, 0.0, 60.0, mcu_at)
    start = 1860.0  # 30 min without telemetry, then a clock 5 ppm faster than before

    def later(host_ns: float) -> int:
        return mcu_at(start * 1e9) + int((host_ns - start * 1e9) * (1 + 25e-6) / 1000)

    feed_at(env, rng, start, 60.0, later)
    est = env.estimate()
    assert est is not None
    assert est.bins <= 3 * 58  # this minute's only
    assert abs(drift_ppm_of(est.ns_per_tick) - 25.0) < 3 * (est.variance**0.5 / 1000.0 * 1e6)


def test_a_floor_that_moved_for_every_kind_widens_the_variance() -> None:
    still, moved = SkewEnvelope(1000.0), SkewEnvelope(1000.0)
    feed(still, random.Random(23), 0.0, 100.0)
    feed(moved, random.Random(23), 0.0, 100.0, step_from_s=70.0)  # +2 ms from 70 s on
    calm, shifted = still.estimate(), moved.estimate()
    assert calm is not None
    assert shifted is not None
    sigma_ppm = shifted.variance**0.5 / 1000.0 * 1e6
    error_ppm = abs(drift_ppm_of(shifted.ns_per_tick) - DRIFT_PPM)
    assert error_ppm > 5.0  # the step looks like a rate error...
    assert error_ppm < 3 * sigma_ppm  # ...that the variance now owns up to
    assert shifted.shift_variance > 10 * calm.variance
    assert calm.shift_variance < calm.variance


def test_the_controller_and_the_replay_feed_every_telemetry_frame_but_marks() -> None:
    frames: list[object] = [
        EncoderBatch(5_000, 10, 10, 0, 0, (EncoderStep(1000, 1, 1, 0, 0),)),
        EncoderSample(9_000, 12, 12, 0, 0),
        RefMark(9_500, 12),
    ]
    ctrl = controller_factory(loads_config(""), lambda *_: None, MemoryTransport())
    for frame in frames:
        ctrl._on_packet(Packet(1, 0, frame))
    assert ctrl.session.clock.estimate().telemetry_frames == 2
    replay = LinkReplay(sink=_NullSink())
    for seq, frame in enumerate(frames):
        replay.feed("rx", 1_000_000 + seq, encode_frame(frame, seq))
    assert replay.clock.estimate().telemetry_frames == 2


class _NullSink:
    """A sample sink that keeps nothing."""

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """Nothing."""

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """Nothing."""

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """Nothing."""

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """Nothing."""


def test_the_envelope_narrows_the_clocks_uncertainty_ahead() -> None:
    with_telemetry, probes_only = paired_syncs(31)
    ahead = mcu_at(360e9) % WRAP_US  # 300 s past the last probe: the slope's share dominates
    assert with_telemetry.uncertainty_ns(ahead) < 0.8 * probes_only.uncertainty_ns(ahead)
