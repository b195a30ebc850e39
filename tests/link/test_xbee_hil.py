"""HIL over the emulated XBee pair: the daemon's Controller against the firmware in real time.

At the rates the daemon streams over XBee, commands are acknowledged promptly and nothing piles
up on the air. Offered more than the air carries, the modules' buffers overflow and lose replies
as well as telemetry; the daemon then sheds telemetry, and commands get through again.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from hil_sim.links.endpoint import SimPortEndpoint
from hil_sim.links.xbee import AIR_RATE_BPS, CONTROLLER_ADDR64, XBeeModule
from hil_sim.runner import RealtimeRunner, Simulation
from hil_sim.scenario import Scenario
from host.link import Controller
from host.link.session import HOST_CAPABILITIES, SessionConfig
from host.service.wiring import XBEE_SHEDDING, stream_rates
from host.transport import create_transport
from protocol.enums import Stream

# More than the air carries: what the daemon streamed over XBee before the air budget (~130 % of
# the air in single samples), and as much in batches (full batches: encoder ~96 %, the rest ~41 %).
OVERLOAD_HZ = {
    "single": {Stream.ENCODER: 50, Stream.RANGE: 50, Stream.HEAD: 20, Stream.STATUS: 10},
    "batched": {Stream.ENCODER: 300, Stream.RANGE: 100, Stream.HEAD: 10, Stream.STATUS: 10},
}
CAPABILITIES = {"single": 0, "batched": HOST_CAPABILITIES}
COMMAND_EVERY_S = 0.2
ACK_WITHIN_S = 0.5  # a first-try round trip is ~40 ms; one retransmission fits too


@pytest.fixture
async def xbee(
    tmp_path: Path, no_leftover_threads: None, request: pytest.FixtureRequest
) -> AsyncIterator[tuple[Controller, XBeeModule]]:
    """Firmware and plant in real time behind the module pair; the daemon's Controller.

    Parametrised indirectly with "single" or "batched" (the default): what the host offers.
    """
    caps = CAPABILITIES[getattr(request, "param", "batched")]
    runner = RealtimeRunner(Simulation(Scenario(seed=1)))
    endpoint = SimPortEndpoint(runner.port, asyncio.get_running_loop())
    module = XBeeModule(endpoint, api_mode=2, link_path=str(tmp_path / "xb"))
    await module.start()
    runner.start()
    transport = create_transport("xbee", url=module.path, dest_addr64=CONTROLLER_ADDR64, api_mode=2)
    config = SessionConfig(capabilities=caps)
    ctrl = Controller(transport, config, shedding=XBEE_SHEDDING)  # as the daemon wires it
    try:
        yield ctrl, module
    finally:
        await ctrl.close()
        await module.stop()
        runner.stop()


async def _point_head(ctrl: Controller, duration_s: float) -> list[float]:
    """HEAD_SET every COMMAND_EVERY_S for duration_s; each one's time to its ACK."""
    loop = asyncio.get_running_loop()
    end = loop.time() + duration_s
    latencies: list[float] = []
    while loop.time() < end:
        sent = loop.time()
        await ctrl.set_head(0.01 * (len(latencies) % 5), 0.0)
        latencies.append(loop.time() - sent)
        await asyncio.sleep(COMMAND_EVERY_S)
    return latencies


async def _rates_fit(ctrl: Controller, module: XBeeModule, max_share: float) -> None:
    """Five seconds of the daemon's XBee streams with a command every 0.2 s: nothing lost."""
    await ctrl.set_streams(stream_rates("xbee", ranging=True))
    loop = asyncio.get_running_loop()
    stats, counters = ctrl.session.stats, module.counters
    air_before, start = module.air_bytes, loop.time()
    before = (stats.timeouts, stats.rx_lost, counters.up_overflow + counters.down_overflow)
    latencies = await _point_head(ctrl, 5.0)
    air_share = (module.air_bytes - air_before) / (loop.time() - start) / (AIR_RATE_BPS / 8)
    assert max(latencies) < ACK_WITHIN_S, f"acks took up to {max(latencies):.2f} s"
    after = (stats.timeouts, stats.rx_lost, counters.up_overflow + counters.down_overflow)
    assert after == before, "(timeouts, frames lost, module overflows) grew"
    assert air_share < max_share, f"the air is {air_share:.0%} busy"
    assert ctrl.telemetry_scale == 1.0


async def test_daemon_rates_fit_the_air_while_the_clock_sync_converges(
    xbee: tuple[Controller, XBeeModule],
) -> None:
    # The first seconds: probes at 10 Hz (19 % of the air) beside the streams and commands.
    ctrl, module = xbee
    await ctrl.connect()
    await _rates_fit(ctrl, module, 0.95)
    assert ctrl.batch_stats.batches > 0


@pytest.mark.slow
@pytest.mark.timeout(120)
async def test_daemon_rates_fit_the_air_once_the_clock_sync_has_converged(
    xbee: tuple[Controller, XBeeModule],
) -> None:
    ctrl, module = xbee
    await ctrl.connect()
    await ctrl.set_streams(stream_rates("xbee", ranging=True))
    for _ in range(600):
        if ctrl.session.probe_rate.slow:
            break
        await asyncio.sleep(0.1)
    assert ctrl.session.probe_rate.slow, "the clock sync never slowed its probes"
    await _rates_fit(ctrl, module, 0.75)  # 64 % planned, plus the commands


@pytest.mark.parametrize("xbee", ["single", "batched"], indirect=True)
async def test_overloaded_air_sheds_telemetry_and_commands_get_through(
    xbee: tuple[Controller, XBeeModule], request: pytest.FixtureRequest
) -> None:
    ctrl, module = xbee
    await ctrl.connect()
    await ctrl.set_streams(OVERLOAD_HZ[request.node.callspec.params["xbee"]])
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 5.0
    while ctrl.telemetry_scale == 1.0 and loop.time() < deadline:
        await asyncio.sleep(0.1)
    assert module.counters.up_overflow > 0  # the air was overloaded
    assert ctrl.telemetry_scale < 1.0
    await asyncio.sleep(1.0)  # what was in the buffers when the cut arrived has left
    overflow = module.counters.up_overflow
    latencies = await _point_head(ctrl, 3.0)
    assert max(latencies) < ACK_WITHIN_S, f"acks took up to {max(latencies):.2f} s"
    assert ctrl.session.stats.timeouts == 0
    assert module.counters.up_overflow - overflow < 10
