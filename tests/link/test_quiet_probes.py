"""Quiet clock probes from the host's side (PROTOCOL.md §8): pairs when both offer them."""

from __future__ import annotations

import asyncio

import pytest

from host.link.controller import Controller
from host.link.reconnect import BackoffConfig
from host.link.session import SessionConfig
from protocol.enums import Capability, Stream
from tests.link.sim_bridge import SimBridge

QUIET = int(Capability.QUIET_CLOCK_PROBES)
BATCHED = int(Capability.BATCHED_TELEMETRY)


@pytest.mark.parametrize(
    ("host_caps", "fw_caps", "paired"),
    [
        (BATCHED | QUIET, BATCHED | QUIET, True),
        (BATCHED, BATCHED | QUIET, False),  # an older host
        (BATCHED | QUIET, BATCHED, False),  # an older controller
    ],
    ids=["both", "old-host", "old-controller"],
)
async def test_probes_come_in_pairs_only_when_both_offer_them(
    bridge: SimBridge, host_caps: int, fw_caps: int, paired: bool
) -> None:
    bridge.sim.firmware.capabilities = fw_caps
    config = SessionConfig(
        rto_initial_s=0.05,
        capabilities=host_caps,
        clock_sync_interval_s=0.05,
        clock_sync_slow_interval_s=0.05,
    )
    ctrl = Controller(bridge.transport, config, BackoffConfig(0.02, 0.2), seed=3)
    try:
        await ctrl.connect()
        await ctrl.set_streams({Stream.ENCODER: 200, Stream.RANGE: 100})
        for _ in range(100):  # until a few probes were fitted (bounded: ~5 s on a slow machine)
            await asyncio.sleep(0.05)
            if ctrl.session.stats.clock_replies >= 12:
                break
    finally:
        await ctrl.close()
    s = ctrl.session
    stats = s.stats
    assert bool(s.capabilities & QUIET) is paired
    assert bridge.sim.firmware.quiet_probes is paired
    assert stats.clock_replies >= 12
    fitted = stats.clock_replies - stats.clock_pair_firsts
    if paired:
        # Every first's reply sent a second, and only seconds entered the fit.
        assert stats.clock_pair_firsts >= 5
        assert stats.clock_probes >= 2 * stats.clock_pair_firsts - 1
        assert fitted >= stats.clock_pair_firsts - 1
    else:
        assert stats.clock_pair_firsts == 0
    est = s.clock.estimate()
    assert s.clock.ready
    assert est.probes_used + est.filtered + est.outliers + est.inconsistent <= fitted
    # The mapping holds either way: a sample stamp maps to the host time the simulator knew.
    mcu = bridge.sim.firmware.now_us & 0xFFFF_FFFF
    err_ns = abs(s.clock.mcu_to_host_ns(mcu) - bridge.host_ns_of_mcu(s.clock.extend(mcu)))
    assert err_ns < 5_000_000
