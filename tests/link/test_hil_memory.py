"""HIL: the controller API against the firmware mirror and the simulated plant, in memory."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from host.link.common import CommandTimeout, ControllerRejected, LinkEvent, LinkState
from host.link.controller import Controller
from host.link.reconnect import BackoffConfig
from host.link.session import SessionConfig
from host.transport.memory import Impairment
from protocol.enums import NakCode, State, Stream
from tests.link.sim_bridge import SimBridge

CFG = SessionConfig(rto_initial_s=0.05, reply_cache_factor=2)


@pytest.fixture
async def hil() -> AsyncIterator[tuple[SimBridge, Controller, list[LinkEvent]]]:
    bridge = SimBridge()
    bridge.start()
    events: list[LinkEvent] = []
    ctrl = Controller(
        bridge.transport, CFG, BackoffConfig(0.02, 0.2), lambda e, _d: events.append(e), seed=3
    )
    yield bridge, ctrl, events
    await ctrl.close()
    await bridge.stop()


async def test_handshake_and_identity_from_firmware(hil) -> None:  # type: ignore[no-untyped-def]
    bridge, ctrl, _ = hil
    ident = await ctrl.connect()
    assert ident.boot_id == bridge.sim.firmware.boot_id
    assert ident.encoder_counts_per_rev == 4000
    assert ident.mm_per_count == pytest.approx(20 * 12.7 / 4000)


async def test_move_before_home_is_rejected(hil) -> None:  # type: ignore[no-untyped-def]
    _, ctrl, _ = hil
    await ctrl.connect()
    with pytest.raises(ControllerRejected) as info:
        await ctrl.move_to(1000.0, 100.0, 500.0)
    assert info.value.code is NakCode.NOT_HOMED


async def test_home_then_move_reaches_target(hil) -> None:  # type: ignore[no-untyped-def]
    _, ctrl, _ = hil
    await ctrl.connect()
    await ctrl.set_param(8, 200_000)  # HOME_SPEED_UM_S: home faster than the default
    homing = await ctrl.home()
    await homing.done(15.0)
    assert ctrl.snapshot().state is State.READY
    start_mm = ctrl.snapshot().position_mm
    assert start_mm is not None
    move = await ctrl.move_to(start_mm + 100.0, 400.0, 2000.0)
    await move.done(10.0)
    assert ctrl.snapshot().state is State.READY
    assert ctrl.session.stats.timeouts == 0


async def test_clock_sync_against_firmware_clock(hil) -> None:  # type: ignore[no-untyped-def]
    bridge, ctrl, _ = hil
    ctrl.session.config.clock_sync_interval_s = 0.02
    await ctrl.connect()
    await asyncio.sleep(2.0)
    clock = ctrl.session.clock
    assert clock.ready
    mcu = bridge.sim.mcu_time_us
    err_ns = abs(clock.mcu_to_host_ns(mcu) - bridge.host_ns_of_mcu(clock.extend(mcu)))
    # The bridge runs ticks in bursts after each ~1 ms sleep: its own timing limits this.
    assert err_ns < 2_000_000


async def test_encoder_stream_under_lossy_link(hil) -> None:  # type: ignore[no-untyped-def]
    bridge, ctrl, _ = hil
    bridge.transport.rx.impairment = Impairment(loss=0.05)
    bridge.transport.tx.impairment = Impairment(loss=0.05)
    await ctrl.connect()
    await ctrl.set_streams({Stream.ENCODER: 100})
    await asyncio.sleep(1.0)
    stats = ctrl.session.stats
    assert len(ctrl.encoder_ring) > 50
    assert stats.rx_lost > 0
    assert ctrl.link_state is LinkState.UP


async def test_controller_reboot_detected_and_streams_restored(hil) -> None:  # type: ignore[no-untyped-def]
    bridge, ctrl, events = hil
    await ctrl.connect()
    await ctrl.set_streams({Stream.ENCODER: 200})
    # > 256 controller frames: a restarted seq is then unmistakable (batches make them fewer).
    for _ in range(400):
        if ctrl.session.stats.frames_in > 300:
            break
        await asyncio.sleep(0.02)
    old_boot = bridge.sim.firmware.boot_id
    bridge.sim.reset_controller()
    for _ in range(200):
        await asyncio.sleep(0.02)
        ident = ctrl.identity
        if ctrl.link_state is LinkState.UP and ident is not None and ident.boot_id != old_boot:
            break
    assert ctrl.identity is not None
    assert ctrl.identity.boot_id != old_boot
    assert LinkEvent.CONTROLLER_RESET in events
    n = len(ctrl.encoder_ring)
    await asyncio.sleep(0.3)
    assert len(ctrl.encoder_ring) > n  # the stream was switched on again


async def test_a_cancelled_command_whose_frame_was_lost_does_not_block_the_next(hil) -> None:  # type: ignore[no-untyped-def]
    # The controller holds every command behind a missing seq: a request given up by its
    # caller must still reach it, or no later command would ever run.
    bridge, ctrl, _ = hil
    await ctrl.connect()
    bridge.transport.tx.impairment = Impairment(loss=1.0)
    task = asyncio.create_task(ctrl.set_param(8, 150_000))  # HOME_SPEED_UM_S
    await asyncio.sleep(0.02)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    bridge.transport.tx.impairment = Impairment()
    assert await asyncio.wait_for(ctrl.set_param(8, 200_000), 2.0) == 200_000
    assert await asyncio.wait_for(ctrl.get_param(8), 2.0) == 200_000  # both ran, in order
    assert ctrl.link_state is LinkState.UP


async def test_a_command_that_timed_out_costs_a_handshake_not_the_link(hil) -> None:  # type: ignore[no-untyped-def]
    # A command abandoned after its last try leaves a hole the controller's sequence cannot
    # pass (the link itself is up: telemetry and heartbeats flow): the host re-handshakes.
    bridge, ctrl, events = hil
    ctrl.session.config.max_tries = 3
    await ctrl.connect()
    handshakes = ctrl.session.stats.handshakes
    bridge.transport.tx.impairment = Impairment(loss=1.0)
    with pytest.raises(CommandTimeout):
        await ctrl.set_param(8, 150_000)
    bridge.transport.tx.impairment = Impairment()
    for _ in range(100):
        if ctrl.link_state is LinkState.UP and ctrl.session.stats.handshakes > handshakes:
            break
        await asyncio.sleep(0.02)
    assert await asyncio.wait_for(ctrl.set_param(8, 200_000), 2.0) == 200_000
    assert LinkEvent.COMMAND_LOST in events
