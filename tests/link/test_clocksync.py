"""Clock sync estimator: synthetic probes over an XBee-like link, wrap extension, outliers."""

from __future__ import annotations

import random
from dataclasses import dataclass

import pytest

from host.link.clocksync import WRAP_US, ClockSync

DRIFT_PPM = 50.0
OFFSET_US = 3_000_000_000  # about 50 minutes to the first wrap
PROBE_PERIOD_NS = 100_000_000
TARGET_ERROR_NS = 200_000


@dataclass
class SimLink:
    """A controller clock and an asymmetric, jittery, lossy radio link between it and the host.

    The controller answers at its next tick, as the firmware does: a probe waits 0–1 tick there.
    """

    rng: random.Random
    drift_ppm: float = DRIFT_PPM
    offset_us: int = OFFSET_US
    out_base_ns: int = 2_000_000
    out_jitter_ns: float = 3_000_000  # mean of exponential extra delay, host → controller
    back_base_ns: int = 1_900_000  # unobservable: costs (2.0 - 1.9) / 2 = 50 µs of bias
    back_jitter_ns: float = 1_000_000
    loss: float = 0.01
    tick_us: int = 1000  # the controller handles frames every tick_us of its clock (0: at once)

    def mcu_at(self, host_ns: float) -> int:
        """True controller clock (64-bit) at a host time."""
        return self.offset_us + int(host_ns * (1 + self.drift_ppm * 1e-6) / 1000)

    def host_at(self, mcu_us: int) -> float:
        """Host time at which the controller clock reaches a value."""
        return (mcu_us - self.offset_us) * 1000 / (1 + self.drift_ppm * 1e-6)

    def probe(self, t0_ns: int) -> tuple[int, int, int, int] | None:
        """One probe: (t0, reply mcu 32-bit, t1, arrival mcu 32-bit), or None if lost."""
        if self.rng.random() < self.loss or self.rng.random() < self.loss:
            return None
        arrive_ns = t0_ns + self.out_base_ns + self.rng.expovariate(1 / self.out_jitter_ns)
        rx = self.mcu_at(arrive_ns)
        tx = rx - rx % self.tick_us + self.tick_us if self.tick_us else rx
        reply_ns = max(arrive_ns, self.host_at(tx))
        t1 = reply_ns + self.back_base_ns + self.rng.expovariate(1 / self.back_jitter_ns)
        return t0_ns, tx % WRAP_US, int(t1), rx % WRAP_US


def run_probes(sync: ClockSync, link: SimLink, start_ns: int, seconds: float) -> int:
    """Feed probes at 10 Hz; return the host time reached."""
    t = start_ns
    for _ in range(int(seconds * 10)):
        probe = link.probe(t)
        if probe is not None:
            sync.add_probe(*probe)
        t += PROBE_PERIOD_NS
    return t


def worst_error_ns(sync: ClockSync, link: SimLink, t_end: int, rng: random.Random) -> float:
    """Largest mapping error over random sample times in the last second."""
    worst = 0.0
    for _ in range(200):
        host_ns = t_end - rng.uniform(0, 1e9)
        mcu32 = link.mcu_at(host_ns) % WRAP_US
        worst = max(worst, abs(sync.mcu_to_host_ns(mcu32) - host_ns))
    return worst


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
def test_mapping_error_within_target_on_xbee_like_link(seed: int) -> None:
    rng = random.Random(seed)
    link = SimLink(rng)
    sync = ClockSync()
    t = 10**12
    t = run_probes(sync, link, t, 30)  # warm up
    worst = 0.0
    for _ in range(6):
        t = run_probes(sync, link, t, 10)
        worst = max(worst, worst_error_ns(sync, link, t, rng))
    assert worst <= TARGET_ERROR_NS, f"worst mapping error {worst / 1000:.0f} µs"
    est = sync.estimate()
    assert est.drift_ppm == pytest.approx(DRIFT_PPM, abs=5.0)


SERIAL_JITTER_NS = 200_000  # mean extra delay each way, on top of a 23-byte frame at 115200


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_arrival_stamp_removes_the_wait_for_the_controller_tick(seed: int) -> None:
    # A symmetric serial-like link; the controller holds each probe until its next 1 kHz tick
    # (0–1 ms, the phase sweeping slowly with the drift). Taken as part of the outbound leg,
    # that wait maps every stamp early by half of it; the arrival stamp takes it out, and what
    # is left comes from the legs' own jitter, which the fit averages over many probes.
    rng = random.Random(seed)
    link = SimLink(
        rng, drift_ppm=20.0, out_base_ns=1_650_000, back_base_ns=1_650_000, loss=0.0,
        out_jitter_ns=SERIAL_JITTER_NS, back_jitter_ns=SERIAL_JITTER_NS,
    )  # fmt: skip
    stamped, midpoint = ClockSync(), ClockSync()
    t = 10**12
    worst_stamped = worst_midpoint = 0.0
    for second in range(90):
        for _ in range(10):
            probe = link.probe(t)
            assert probe is not None
            t0, mcu, t1, rx = probe
            stamped.add_probe(t0, mcu, t1, rx)
            midpoint.add_probe(t0, mcu, t1)  # what the host did before the arrival stamp
            t += PROBE_PERIOD_NS
        if second >= 30:
            worst_stamped = max(worst_stamped, worst_error_ns(stamped, link, t, rng))
            worst_midpoint = max(worst_midpoint, worst_error_ns(midpoint, link, t, rng))
    assert worst_stamped < SERIAL_JITTER_NS / 4, f"{worst_stamped / 1000:.0f} µs"
    assert worst_midpoint > SERIAL_JITTER_NS / 2, f"{worst_midpoint / 1000:.0f} µs"
    assert stamped.estimate().inconsistent == 0


def test_a_reply_held_longer_than_its_round_trip_is_ignored() -> None:
    rng = random.Random(13)
    link = SimLink(rng, loss=0.0)
    sync = ClockSync()
    t = run_probes(sync, link, 0, 5)
    used = sync.probes_used
    mcu = link.mcu_at(t + 2_000_000)
    assert not sync.add_probe(t, mcu % WRAP_US, t + 4_000_000, (mcu - 5_000) % WRAP_US)
    assert not sync.add_probe(t, mcu % WRAP_US, t + 4_000_000, (mcu + 1) % WRAP_US)  # after
    assert sync.estimate().inconsistent == 2
    assert sync.probes_used == used


def test_uncertainty_tracks_the_real_error() -> None:
    rng = random.Random(11)
    link = SimLink(rng)
    sync = ClockSync()
    t = run_probes(sync, link, 0, 60)
    sigma = sync.uncertainty_ns()
    err = worst_error_ns(sync, link, t, rng)
    assert 1_000 < sigma < 200_000
    assert err < 10 * sigma + 100_000  # the asymmetry bias is invisible to any estimator


def test_extend_crosses_the_32_bit_wrap() -> None:
    sync = ClockSync()
    assert sync.extend(WRAP_US - 10) == WRAP_US - 10
    assert sync.extend(5) == WRAP_US + 5
    assert sync.extend(WRAP_US - 20) == WRAP_US - 20  # slightly older sample: no false wrap
    assert sync.extend(100) == WRAP_US + 100
    assert sync.extend(WRAP_US - 1) == WRAP_US - 1  # older, within half a wrap
    assert sync.extend((1 << 31) + 50) == WRAP_US + (1 << 31) + 50  # newer, within half


def test_mapping_is_continuous_across_the_wrap() -> None:
    rng = random.Random(7)
    link = SimLink(rng, offset_us=WRAP_US - 20_000_000, loss=0.0)  # wraps 20 s in
    sync = ClockSync()
    t = run_probes(sync, link, 0, 60)
    assert link.mcu_at(t) > WRAP_US
    host_ns = t - 500_000_000
    assert abs(sync.mcu_to_host_ns(link.mcu_at(host_ns) % WRAP_US) - host_ns) < TARGET_ERROR_NS


def test_inverse_mapping_round_trips() -> None:
    rng = random.Random(3)
    link = SimLink(rng, loss=0.0)
    sync = ClockSync()
    t = run_probes(sync, link, 0, 20)
    mcu = sync.host_to_mcu(t)
    assert abs(mcu - link.mcu_at(t)) < 200
    assert abs(sync.ext_to_host_ns(mcu) - t) < 2_000


def test_wild_probe_is_rejected_and_counted() -> None:
    rng = random.Random(5)
    link = SimLink(rng, loss=0.0)
    sync = ClockSync()
    t = run_probes(sync, link, 0, 20)
    bogus_mcu = (link.mcu_at(t) + 50_000) % WRAP_US  # 50 ms off with a short RTT
    assert not sync.add_probe(t, bogus_mcu, t + 3_800_000)
    assert sync.estimate().outliers == 1


def test_clock_step_restarts_the_fit() -> None:
    rng = random.Random(9)
    link = SimLink(rng, loss=0.0)
    sync = ClockSync()
    t = run_probes(sync, link, 0, 20)
    link.offset_us += 10_000_000
    t = run_probes(sync, link, t, 20)
    host_ns = t - 300_000_000
    assert abs(sync.mcu_to_host_ns(link.mcu_at(host_ns) % WRAP_US) - host_ns) < TARGET_ERROR_NS


def test_mapping_before_any_probe_is_a_clear_error() -> None:
    with pytest.raises(RuntimeError, match="no probe"):
        ClockSync().mcu_to_host_ns(0)
    with pytest.raises(ValueError, match="mcu_clock_hz"):
        ClockSync(mcu_clock_hz=0)
    assert not ClockSync().add_probe(10, 0, 5)  # negative RTT


def test_known_base_asymmetry_is_corrected_by_outbound_fraction() -> None:
    rng = random.Random(21)
    link = SimLink(rng, out_base_ns=3_000_000, back_base_ns=1_000_000)  # 1 ms of pure bias
    naive, told = ClockSync(), ClockSync(outbound_fraction=0.75)
    t = 0
    for _ in range(600):
        probe = link.probe(t)
        if probe is not None:
            naive.add_probe(*probe)
            told.add_probe(*probe)
        t += PROBE_PERIOD_NS
    assert worst_error_ns(naive, link, t, rng) > 800_000
    assert worst_error_ns(told, link, t, rng) < TARGET_ERROR_NS


def test_a_peek_maps_as_the_link_does_and_leaves_the_extension_alone() -> None:
    rng = random.Random(7)
    link = SimLink(rng, offset_us=WRAP_US - 20_000_000, loss=0.0)  # wraps 20 s in
    sync = ClockSync()
    t = run_probes(sync, link, 0, 60)
    ahead = (link.mcu_at(t) + 1_000_000) % WRAP_US  # a second past the newest stamp
    before = sync._last_ext
    assert sync.peek_host_ns(ahead) == sync.ext_to_host_ns(sync._extend_query(ahead))
    assert sync._last_ext == before  # a score must not move the link's own reference
    assert sync.mcu_to_host_ns(ahead) == sync.peek_host_ns(ahead)
