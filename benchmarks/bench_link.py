"""Link session figures: command throughput over the in-memory transport, clock-sync accuracy.

The synthetic clock-sync link is XBee-like, and its controller answers a probe at its next 1 kHz
tick (a 0–1 ms wait), as the firmware does. Beside our estimator, the same probes go to two
peers: ours without the controller's arrival stamp (the round-trip midpoint, what a controller
that cannot stamp arrivals gets) and a naive midpoint fit.

The telemetry-envelope section feeds 1 Hz probes whose legs split unevenly by an amount that
changes every 15 s (the half-duplex radio's bias no round trip shows) to our estimator with the
telemetry's arrivals (three kinds of frame, ~47 a second, each with its own floor) beside the same
probes alone, and prints the fitted rate's error after 60 s and what the envelope costs.

Run: python benchmarks/bench_link.py   (prints `metric: value` lines)
"""

from __future__ import annotations

import asyncio
import random
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from host.link.clocksync import WRAP_US, ClockSync
from host.link.session import Session, SessionConfig
from host.transport.memory import Impairment
from protocol.messages import ParamSet
from tests.link.fake_controller import FakeController
from tests.link.test_clocksync import SimLink, run_probes
from tests.link.test_skew import DRIFT_PPM, feed, mcu_at, paired_syncs

COMMANDS = 2000


async def command_rate(loss: float) -> tuple[float, int]:
    """Acknowledged commands per second, and retransmissions, at a given loss each way."""
    fake = FakeController(rx_window=8)
    imp = Impairment(loss=loss)
    transport = fake.wire(tx=imp, rx=imp)
    await transport.open()
    cfg = SessionConfig(rto_initial_s=0.01, rto_min_s=0.005, max_tries=30, reply_cache_factor=2)
    session = Session(transport, cfg)
    session.start()
    await session.handshake()
    t0 = time.perf_counter()
    await asyncio.gather(*(session.request(ParamSet(2, i)) for i in range(COMMANDS)))
    rate = COMMANDS / (time.perf_counter() - t0)
    await session.stop()
    await transport.close()
    return rate, session.stats.retransmits


class NaiveMidpoint:
    """The peer: every probe's RTT midpoint, one least-squares line over the last 10 s.

    What a first attempt does (no arrival stamp, no minimum-delay selection, no decay, no outlier
    rejection).
    """

    WINDOW = 100  # probes: 10 s at 10 Hz

    def __init__(self) -> None:
        self.samples: list[tuple[int, float]] = []
        self._last = 0

    def add_probe(self, t0_ns: int, mcu_us: int, t1_ns: int, rx_us: int | None = None) -> bool:
        """Take the probe as (mcu µs extended past its wrap, midpoint ns); ignore the arrival."""
        self.samples.append((self._extend(mcu_us), (t0_ns + t1_ns) / 2))
        del self.samples[: -self.WINDOW]
        return True

    def mcu_to_host_ns(self, mcu_us: int) -> int:
        """Host ns of an MCU stamp by the fitted line."""
        xs = [m for m, _ in self.samples]
        ys = [h for _, h in self.samples]
        mx, my = statistics.fmean(xs), statistics.fmean(ys)
        slope = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sum(
            (x - mx) ** 2 for x in xs
        )
        return round(my + slope * (self._extend(mcu_us, advance=False) - mx))

    def _extend(self, mcu_us: int, advance: bool = True) -> int:
        """32-bit stamp → 64-bit, by the signed difference from the last one."""
        diff = (mcu_us - self._last + (1 << 31)) % WRAP_US - (1 << 31)
        value = self._last + diff if self.samples or not advance else mcu_us
        if advance:
            self._last = value
        return value


class WithoutArrivalStamp(ClockSync):
    """Our estimator fed as by a controller that cannot stamp arrivals (rx = reply time)."""

    def add_probe(
        self, t0_ns: int, mcu_ticks_32: int, t1_ns: int, rx_ticks_32: int | None = None
    ) -> bool:
        """Drop the arrival stamp."""
        return super().add_probe(t0_ns, mcu_ticks_32, t1_ns)


PEERS: dict[str, type[Any]] = {
    "ours": ClockSync,
    "no_rx": WithoutArrivalStamp,
    "naive": NaiveMidpoint,
}


def clock_errors_us(seeds: int = 20, peer: str = "ours") -> list[float]:
    """Worst mapping error per seeded run of the XBee-like synthetic link."""
    worst = []
    for seed in range(seeds):
        rng = random.Random(seed)
        link = SimLink(rng)
        sync: Any = PEERS[peer]()
        t = run_probes(sync, link, 0, 90)
        errs = []
        for _ in range(200):
            host_ns = t - rng.uniform(0, 1e9)
            errs.append(abs(sync.mcu_to_host_ns(link.mcu_at(host_ns) % WRAP_US) - host_ns))
        worst.append(max(errs) / 1000)
    return worst


def probe_cost_us() -> float:
    """CPU time of one add_probe with a full history."""
    rng = random.Random(1)
    link, sync = SimLink(rng, loss=0.0), ClockSync()
    t = run_probes(sync, link, 0, 90)
    t0 = time.perf_counter()
    run_probes(sync, link, t, 10)
    return (time.perf_counter() - t0) / 100 * 1e6


def envelope_rate_errors_ppm(seeds: int = 10) -> tuple[list[float], list[float]]:
    """|fitted rate − true| after 60 s of biased 1 Hz probes: with telemetry, and probes alone."""
    with_tele, alone = [], []
    for seed in range(seeds):
        sync, bare = paired_syncs(seed)
        with_tele.append(abs(sync.estimate().drift_ppm - DRIFT_PPM))
        alone.append(abs(bare.estimate().drift_ppm - DRIFT_PPM))
    return with_tele, alone


def envelope_costs_us() -> tuple[float, float]:
    """CPU per telemetry frame (add_arrival), and per refit of a full envelope (two minutes of
    three kinds), which a used probe pays at most once per closed second."""
    sync, rng = ClockSync(), random.Random(3)
    feed(sync, rng, 0.0, 130.0)
    stamps = [(mcu_at(130e9 + i * 2e7) % WRAP_US, int(130e9 + i * 2e7 + 9e6)) for i in range(5000)]
    t0 = time.perf_counter()
    for mcu, arrival in stamps:
        sync.add_arrival("enc", mcu, arrival)
    per_frame = (time.perf_counter() - t0) / len(stamps) * 1e6
    envelope = sync._skew
    t0 = time.perf_counter()
    for _ in range(50):
        envelope._fit()
    return per_frame, (time.perf_counter() - t0) / 50 * 1e6


def main() -> None:
    for loss in (0.0, 0.1):
        rate, retx = asyncio.run(command_rate(loss))
        print(f"link_commands_per_s_loss_{int(loss * 100)}pct: {rate:.0f}")
        print(f"link_retransmits_loss_{int(loss * 100)}pct: {retx}")
    worst = clock_errors_us()
    no_rx = clock_errors_us(peer="no_rx")
    naive = clock_errors_us(peer="naive")
    print(f"clocksync_xbee_worst_error_us_median: {statistics.median(worst):.0f}")
    print(f"clocksync_no_rx_stamp_xbee_worst_error_us_median: {statistics.median(no_rx):.0f}")
    print(f"naive_midpoint_xbee_worst_error_us_median: {statistics.median(naive):.0f}")
    print(f"clocksync_xbee_worst_error_us_max: {max(worst):.0f}")
    print(f"clocksync_no_rx_stamp_xbee_worst_error_us_max: {max(no_rx):.0f}")
    print(f"naive_midpoint_xbee_worst_error_us_max: {max(naive):.0f}")
    print(f"clocksync_add_probe_us: {probe_cost_us():.0f}")
    with_tele, alone = envelope_rate_errors_ppm()
    print(f"clocksync_biased_probes_rate_error_ppm_median: {statistics.median(alone):.2f}")
    print(f"clocksync_with_telemetry_rate_error_ppm_median: {statistics.median(with_tele):.2f}")
    print(f"clocksync_biased_probes_rate_error_ppm_max: {max(alone):.2f}")
    print(f"clocksync_with_telemetry_rate_error_ppm_max: {max(with_tele):.2f}")
    per_frame, per_probe = envelope_costs_us()
    print(f"clocksync_add_arrival_us: {per_frame:.1f}")
    print(f"clocksync_envelope_refit_us: {per_probe:.0f}")


if __name__ == "__main__":
    main()
