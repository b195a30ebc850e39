"""Long runs under faults on every link (`-m slow`): losses seen by the host match the injected."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

import pytest

from hil_sim.links.faults import FaultConfig
from tests.transport.harness import ALL_LINKS, Collector, Link

SOAK_FRAMES = 3000
PERIOD_S = 0.004  # below every link's capacity, XBee's included


@pytest.mark.slow
@pytest.mark.parametrize("link_cls", ALL_LINKS, ids=lambda c: c.name)
async def test_soak_under_loss_and_bursts(link_cls: Callable[..., Link], tmp_path: Path) -> None:
    faults = FaultConfig(drop_rate=0.05, burst_rate=0.005, burst_length_mean=4.0, seed=99)
    link = link_cls(tmp_path, faults_to_host=faults)
    await link.start()
    transport = link.transport()
    rx = Collector()
    rx.attach(transport)
    await transport.open()
    try:
        for i in range(SOAK_FRAMES):
            link.controller.send_sample(i)
            await asyncio.sleep(PERIOD_S)
        due = SOAK_FRAMES - link.frames_lost_to_host()
        await rx.wait_packets(due, timeout_s=60.0)
        await rx.settle(quiet_s=0.2)
        assert len(rx.packets) == due
        seqs = [p.seq for p in rx.packets]
        assert seqs == sorted(set(seqs))
        assert rx.decoder.drops.total() == 0
    finally:
        await transport.close()
        await link.stop()
