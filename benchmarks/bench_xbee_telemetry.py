"""XBee telemetry section of the link benchmark: single samples beside batches, same run.

    python benchmarks/bench_xbee_telemetry.py [--modes single batched ages_20_40]  # ~50 s a mode
    python benchmarks/bench_link_transport.py --telemetry  # the same, from the transport bench

The daemon's Controller talks to the firmware mirror and the simulated plant running in real
time behind the emulated XBee pair (API mode 2, 35 kbit/s air, checked against Digi's figures
in `hil_sim.links.xbee`, 202-byte module buffers), with the daemon's XBee rates for
the mode: single samples (a host that does not offer batching, at `SINGLE_SAMPLE_RATES_HZ`),
batched (both offer it, at the batched rates and the link's batch ages) and `ages_E_R` (the
same with other batch ages: the latency/air trade; `--modes`). Each mode waits for the steady
state (the clock sync's probes slowed down and no shedding; at most `SETTLE_MAX_S`, its time
printed as `settle_s`), then measures for `MEASURE_S`:

- `<mode>.encoder_hz`, `<mode>.range_hz`: samples that reached the host's buffers per second;
- `<mode>.air_share`: the air's busy time (every MAC attempt with its overhead, both ways);
- `<mode>.clock_sync_air_share`: the probes' and replies' part of it; `heartbeat_air_share`: the
  host's heartbeats' (they fill its silences, every WATCHDOG_MS / 4);
- `<mode>.sample_age_p50_ms` / `_p95_ms` (encoder), `range_age_p95_ms`: host arrival time
  minus the sample's MCU stamp mapped to host time (what the buffers index it by);
- `<mode>.clock_error_p95_us`, `clock_error_max_us`: the clock mapping against the simulator's
  true crystal, sampled every 0.5 s while measuring; `clock_probe_hz`: probes sent per second;
- `<mode>.lost_frames`, `module_overflows`: controller frames lost, and lost in a full buffer.

The emulator runs in this process (a thread for the plant and firmware), so no CPU figure is
given here; the transport section above has those.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil_sim.links.endpoint import SimPortEndpoint
from hil_sim.links.xbee import AIR_OVERHEAD_BYTES, AIR_RATE_BPS, CONTROLLER_ADDR64, XBeeModule
from hil_sim.runner import RealtimeRunner, Simulation
from hil_sim.scenario import Scenario
from host.link import Controller
from host.link.batches import TelemetryPlan, plan_for
from host.link.session import SessionConfig
from host.service.wiring import XBEE_SHEDDING, stream_rates
from host.transport import create_transport
from protocol import encode_frame
from protocol.enums import Stream
from protocol.messages import ClockSync, ClockSyncReply, Heartbeat

SETTLE_MAX_S = 60.0  # waits at most this long for the steady state
MEASURE_S = 20.0
CLOCK_CHECK_S = 0.5
HEARTBEAT_AIR_BYTES = len(encode_frame(Heartbeat(0), 0)) + AIR_OVERHEAD_BYTES
PROBE_PAIR_AIR_BYTES = (
    len(encode_frame(ClockSync(0), 0)) + len(encode_frame(ClockSyncReply(0, 0, 0, 0), 0))
) + 2 * AIR_OVERHEAD_BYTES
# The daemon's two cases, then the trade-off: `ages_E_R` batches encoder samples for at most E ms
# and range samples for R ms (head alone), at the same rates: shorter ages, younger samples, more
# air. (At 100 Hz an age between two multiples of 10 ms adds wait and saves no packet.)
MODES = ("single", "batched", "ages_20_40", "ages_30_60")


def plan_of(mode: str) -> TelemetryPlan | None:
    """The batch ages of a mode (None: the daemon's plan for XBee)."""
    if not mode.startswith("ages_"):
        return plan_for("xbee")
    enc, rng = (int(x) for x in mode.removeprefix("ages_").split("_"))
    return TelemetryPlan({Stream.ENCODER: enc, Stream.RANGE: rng, Stream.HEAD: 0})


class AgeSink:
    """A SampleSink noting each sample's age: host arrival minus its mapped MCU stamp."""

    def __init__(self) -> None:
        self.encoder_ms: list[float] = []
        self.range_ms: list[float] = []
        self.recording = False

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        """One encoder sample."""
        if self.recording:
            self.encoder_ms.append((time.monotonic_ns() - t_host_ns) / 1e6)

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """One range sample."""
        if self.recording:
            self.range_ms.append((time.monotonic_ns() - t_host_ns) / 1e6)

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """Head samples are not timed here."""

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """Marks are not timed here."""


def clock_error_us(ctrl: Controller, runner: RealtimeRunner) -> float | None:
    """The mapping's error now: where it puts the MCU time of this instant, minus this instant."""
    clock = ctrl.session.clock
    if not clock.ready:
        return None
    now_ns = time.monotonic_ns()
    mcu_us = runner.sim.board.mcu_us_at(runner.true_s_at(now_ns))
    return (clock.mcu_to_host_ns(mcu_us & 0xFFFF_FFFF) - now_ns) / 1e3


def _pct(values: list[float], q: float) -> float:
    """Nearest-rank percentile (nan when empty)."""
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


async def run_mode(mode: str, tmp: str) -> dict[str, float | int]:
    """One mode's figures."""
    batched = mode != "single"
    plan = plan_of(mode)
    runner = RealtimeRunner(Simulation(Scenario(seed=1)))
    loop = asyncio.get_running_loop()
    module = XBeeModule(SimPortEndpoint(runner.port, loop), 2, link_path=f"{tmp}/xb-{mode}")
    await module.start()
    runner.start()
    transport = create_transport("xbee", url=module.path, dest_addr64=CONTROLLER_ADDR64, api_mode=2)
    config = SessionConfig() if batched else SessionConfig(capabilities=0)
    ctrl = Controller(transport, config, shedding=XBEE_SHEDDING, telemetry_plan=plan)
    sink = AgeSink()
    ctrl.add_sink(sink)
    try:
        await ctrl.connect()  # the batch ages: the Controller's plan for an XBee transport
        await ctrl.set_streams(stream_rates("xbee", ranging=True, batched=batched))
        settle_s = await _settle(ctrl)
        return {"settle_s": settle_s, **await _measure(ctrl, module, runner, sink)}
    finally:
        await ctrl.close()
        await module.stop()
        runner.stop()


async def _settle(ctrl: Controller) -> float:
    """Seconds until the probes run slow and the streams at full rate (or SETTLE_MAX_S)."""
    start = time.monotonic()
    steady = 0
    while (elapsed := time.monotonic() - start) < SETTLE_MAX_S and steady < 3:
        await asyncio.sleep(1.0)
        ok = ctrl.session.probe_rate.slow and ctrl.telemetry_scale == 1.0
        steady = steady + 1 if ok else 0
    return elapsed


async def _measure(
    ctrl: Controller, module: XBeeModule, runner: RealtimeRunner, sink: AgeSink
) -> dict[str, float | int]:
    """Counters before and after MEASURE_S of streaming, and the clock error meanwhile."""
    stats = ctrl.session.stats
    air0, probes0, lost0 = module.air_bytes, stats.clock_probes, stats.rx_lost
    beats0 = stats.heartbeats_out
    overflow0 = module.counters.up_overflow + module.counters.down_overflow
    start = time.monotonic()
    sink.recording = True
    errors: list[float] = []
    while (elapsed := time.monotonic() - start) < MEASURE_S:
        await asyncio.sleep(min(CLOCK_CHECK_S, MEASURE_S - elapsed))
        err = clock_error_us(ctrl, runner)
        if err is not None:
            errors.append(abs(err))
    sink.recording = False
    span = time.monotonic() - start
    air_rate = AIR_RATE_BPS / 8
    probes = stats.clock_probes - probes0
    beats = stats.heartbeats_out - beats0
    overflow = module.counters.up_overflow + module.counters.down_overflow - overflow0
    return {
        "encoder_hz": len(sink.encoder_ms) / span,
        "range_hz": len(sink.range_ms) / span,
        "air_share": (module.air_bytes - air0) / span / air_rate,
        "clock_sync_air_share": probes * PROBE_PAIR_AIR_BYTES / span / air_rate,
        "clock_probe_hz": probes / span,
        "heartbeat_air_share": beats * HEARTBEAT_AIR_BYTES / span / air_rate,
        "sample_age_p50_ms": statistics.median(sink.encoder_ms) if sink.encoder_ms else 0.0,
        "sample_age_p95_ms": _pct(sink.encoder_ms, 0.95),
        "range_age_p95_ms": _pct(sink.range_ms, 0.95),
        "clock_error_p95_us": _pct(errors, 0.95),
        "clock_error_max_us": max(errors, default=float("nan")),
        "lost_frames": stats.rx_lost - lost0,
        "module_overflows": overflow,
        "telemetry_scale": ctrl.telemetry_scale,
    }


async def section_xbee_telemetry(modes: tuple[str, ...] = MODES) -> dict[str, dict[str, Any]]:
    """Print `telemetry.xbee.<mode>.<metric>: value` for each mode, side by side."""
    out: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in modes:
            out[mode] = figures = await run_mode(mode, tmp)
            for name, value in figures.items():
                shown = f"{value:.3f}" if isinstance(value, float) else str(value)
                print(f"telemetry.xbee.{mode}.{name}: {shown}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the section on its own."""
    parser = argparse.ArgumentParser(description="XBee telemetry: single samples beside batches")
    parser.add_argument("--modes", nargs="*", default=list(MODES), help="single, batched, ages_E_R")
    args = parser.parse_args(argv)
    asyncio.run(section_xbee_telemetry(tuple(args.modes)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
