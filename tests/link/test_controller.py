"""Controller API over the fake: units, NAK, motion completion, samples, reconnect and reset."""

from __future__ import annotations

import asyncio
import math
import struct
from collections.abc import AsyncIterator

import pytest

from host.link.common import BadIdentity, ControllerRejected, LinkDown, LinkEvent, LinkState
from host.link.controller import Controller, MotionFailed
from host.link.reconnect import BackoffConfig
from host.link.session import Session, SessionConfig
from host.link.shedding import SheddingConfig
from protocol import PROTOCOL_VERSION, SCHEMA, ParamId, cobs
from protocol.crc import frame_crc
from protocol.enums import NakCode, State, Stream
from protocol.messages import HeadSample, Identify, MoveTo, Status, StreamSet
from tests.link.fake_controller import FakeController

CFG = SessionConfig(rto_initial_s=0.02, heartbeat_interval_s=0.02, dead_after_heartbeats=10)
BACKOFF = BackoffConfig(initial_s=0.02, max_s=0.1)


class Sink:
    """Records encoder samples."""

    def __init__(self) -> None:
        self.encoder: list[tuple[int, float, float, int]] = []

    def on_encoder(self, t_host_ns: int, s_mm: float, velocity_mm_s: float, inputs: int) -> None:
        self.encoder.append((t_host_ns, s_mm, velocity_mm_s, inputs))

    def on_head(self, t_host_ns: int, pan_rad: float, tilt_rad: float) -> None:
        """Unused here."""

    def on_range(self, t_host_ns: int, distance_mm: float, quality: int) -> None:
        """Unused here."""

    def on_mark(self, t_host_ns: int, s_mm: float) -> None:
        """Unused here."""


@pytest.fixture
async def rig() -> AsyncIterator[tuple[FakeController, Controller, list[LinkEvent]]]:
    fake = FakeController()
    events: list[LinkEvent] = []
    ctrl = Controller(fake.wire(), CFG, BACKOFF, on_event=lambda e, _d: events.append(e), seed=1)
    await ctrl.connect()
    yield fake, ctrl, events
    await ctrl.close()
    await fake.close()


async def test_move_converts_units_and_completes_on_status(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    motion = await ctrl.move_to(1500.0, 100.0, 250.5)
    assert fake.executed[-1] == MoveTo(1_500_000, 100_000, 250_500)
    waiter = asyncio.create_task(motion.done(2.0))
    fake.send_status(State.MOVING, 700_000, 1_500_000)
    fake.send_status(State.READY, 700_000, 700_000)  # at rest, but not this motion's target
    await asyncio.sleep(0.01)
    assert not waiter.done()
    fake.send_status(State.READY, 1_500_010, 1_500_000)
    await waiter
    snap = ctrl.snapshot()
    assert snap.state is State.READY
    assert snap.position_mm == pytest.approx(1500.01)
    assert snap.link is LinkState.UP


async def test_motion_fault_raises(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    motion = await ctrl.jog(50.0, 100.0)
    fake.send_status(State.FAULT, 0, 0)
    with pytest.raises(MotionFailed, match="FAULT"):
        await motion.done(1.0)


async def test_nak_raises_controller_rejected(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    fake.nak_next = (NakCode.NOT_HOMED, State.IDLE)
    with pytest.raises(ControllerRejected) as info:
        await ctrl.move_to(10.0, 10.0, 10.0)
    assert (info.value.code, info.value.state) == (NakCode.NOT_HOMED, State.IDLE)


async def test_encoder_samples_reach_sinks_in_mm_and_host_time(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    sink = Sink()
    ctrl.add_sink(sink)
    await asyncio.sleep(0.35)  # a few clock-sync probes
    assert ctrl.session.clock.ready
    # The MCU clock is 32 bits: wrap it as the controller would (the host's uptime may exceed it).
    now_us = (int(asyncio.get_running_loop().time() * 1e6) + fake.mcu_offset_us) & 0xFFFF_FFFF
    fake.send_encoder(now_us, 4000, 400)  # one sprocket turn: 20 teeth × 12.7 mm
    await asyncio.sleep(0.01)
    _t_ns, s_mm, v_mm_s, _ = sink.encoder[-1]
    assert s_mm == pytest.approx(254.0)
    assert v_mm_s == pytest.approx(25.4)
    assert ctrl.encoder_ring[-1][1] == pytest.approx(254.0)


async def test_the_snapshot_says_how_old_its_head_sample_is(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    assert ctrl.snapshot()["head_age_s"] is None  # no head sample yet
    await asyncio.sleep(0.35)  # a few clock-sync probes
    now_us = (int(asyncio.get_running_loop().time() * 1e6) + fake.mcu_offset_us) & 0xFFFF_FFFF
    fake.send(HeadSample(now_us - 30_000, 785_398, -174_533))  # exposed 30 ms ago
    await asyncio.sleep(0.01)
    first = ctrl.snapshot()
    assert first["head_rad"] == [0.7854, -0.17453]
    assert 0.03 <= first["head_age_s"] < 0.2
    await asyncio.sleep(0.05)
    again = ctrl.snapshot()  # the same sample, older by the wait
    assert again["head_age_s"] - first["head_age_s"] == pytest.approx(
        (again.taken_ns - first.taken_ns) / 1e9, abs=1e-5
    )


async def test_reconnect_with_backoff_refuses_commands_meanwhile(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    await ctrl.set_streams({Stream.ENCODER: 100})
    stream_sets = sum(isinstance(m, StreamSet) for m in fake.executed)
    fake.silent = True
    pending = asyncio.create_task(ctrl.stop())
    await asyncio.sleep(0.005)
    fake.transport.available = False
    fake.transport.disconnect()
    with pytest.raises(LinkDown):
        await pending  # failed, never re-sent after the reconnect
    assert ctrl.link_state in (LinkState.DOWN, LinkState.BACKOFF)
    with pytest.raises(LinkDown):
        await ctrl.move_to(1.0, 1.0, 1.0)
    await asyncio.sleep(0.3)
    attempts = ctrl.supervisor.attempts
    assert attempts >= 3  # retried with backoff while the device was missing
    fake.silent = False
    fake.transport.available = True
    for _ in range(100):
        await asyncio.sleep(0.02)
        if ctrl.link_state is LinkState.UP:
            break
    assert ctrl.link_state is LinkState.UP
    assert sum(isinstance(m, StreamSet) for m in fake.executed) == stream_sets + 2  # both restored
    assert not any(type(m).__name__ == "Stop" for m in fake.executed)


async def test_controller_reset_is_detected_and_state_restored(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, events = rig
    await ctrl.set_streams({Stream.ENCODER: 200})
    await ctrl.set_param(2, 123_000)
    fake.send_heartbeat(5000)
    fake.reboot(0xBEEF)
    fake.send_heartbeat(10)
    for _ in range(100):
        await asyncio.sleep(0.02)
        if ctrl.link_state is LinkState.UP and ctrl.identity and ctrl.identity.boot_id == 0xBEEF:
            break
    assert LinkEvent.CONTROLLER_RESET in events
    assert fake.streams == {int(Stream.STATUS): 20, int(Stream.ENCODER): 200}
    assert fake.params == {2: 123_000}
    assert ctrl.session.stats.controller_resets == 1


async def test_the_handshake_after_a_reset_starts_from_the_measured_rto(rig) -> None:  # type: ignore[no-untyped-def]
    """Timeouts of commands a rebooted controller never answered are not the link's: the HELLO
    goes out at the RTO the samples give, not one backed off to rto_max_s."""
    fake, ctrl, _ = rig
    session: Session = ctrl.session
    measured = session.rto.rto_s
    for _ in range(8):
        session.rto.backoff()  # as the commands in flight at the reboot timed out
    assert session.rto.rto_s == session.config.rto_max_s
    at_hello: list[float] = []
    handshake = session.handshake

    async def recording() -> tuple[Identify, bool]:
        at_hello.append(session.rto.rto_s)
        return await handshake()

    session.handshake = recording  # type: ignore[method-assign]
    fake.send_heartbeat(5000)
    fake.reboot(0xBEEF)
    fake.send_heartbeat(10)  # uptime fell: reset suspected
    for _ in range(100):
        await asyncio.sleep(0.02)
        if ctrl.link_state is LinkState.UP and ctrl.identity and ctrl.identity.boot_id == 0xBEEF:
            break
    assert at_hello
    assert at_hello[0] == pytest.approx(measured)


async def test_heartbeat_silence_drops_then_recovers(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, events = rig
    fake.silent = True
    await asyncio.sleep(0.3)
    assert LinkEvent.HEARTBEAT_TIMEOUT in events
    assert ctrl.link_state is not LinkState.UP
    fake.silent = False
    for _ in range(100):
        await asyncio.sleep(0.02)
        if ctrl.link_state is LinkState.UP:
            break
    assert ctrl.link_state is LinkState.UP


async def test_unknown_state_in_status_does_not_break_the_snapshot(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    # A newer firmware's state and fault bit: out of our encoder's range, so built by hand.
    raw = struct.pack("<BBHB", PROTOCOL_VERSION, 0, 1234, SCHEMA.by_cls[Status].id)
    raw += struct.pack("<IBHBiiH", 0, 99, 0x4000, 0x10, 1000, 1000, 0)
    fake.transport.inject(cobs.encode(raw + frame_crc(raw).to_bytes(2, "big")) + b"\x00")
    await asyncio.sleep(0.01)
    snap = ctrl.snapshot()
    assert snap.state == 99
    assert snap.position_mm == pytest.approx(1.0)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
async def test_non_finite_targets_are_refused_before_anything_is_sent(rig, bad: float) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    before = len(fake.executed)
    with pytest.raises(ValueError, match="finite"):
        await ctrl.move_to(bad, 100.0, 100.0)
    with pytest.raises(ValueError, match="finite"):
        await ctrl.set_head(0.0, bad)
    assert len(fake.executed) == before


async def test_identify_with_zero_constants_is_refused() -> None:
    fake = FakeController(counts_per_rev=0)
    ctrl = Controller(fake.wire(), CFG, BACKOFF, seed=1)
    with pytest.raises(BadIdentity, match="encoder_counts_per_rev"):
        await ctrl.connect()
    await ctrl.close()
    await fake.close()


async def test_a_motion_across_a_controller_reboot_fails_at_once(rig) -> None:  # type: ignore[no-untyped-def]
    fake, ctrl, _ = rig
    motion = await ctrl.jog(50.0, 100.0)
    waiter = asyncio.create_task(motion.done(30.0))
    fake.send_heartbeat(5000)
    fake.reboot(0xBEEF)
    fake.send_heartbeat(10)
    # LinkDown while the host re-handshakes, MotionFailed if the new IDENTIFY came first:
    # either way at once, never after the motion's 30 s timeout.
    with pytest.raises((MotionFailed, LinkDown)):
        await asyncio.wait_for(waiter, 5.0)


SHED = SheddingConfig(window_s=0.05, min_frames=5, clean_s=0.1)


async def test_lost_frames_shed_the_streams_until_the_link_is_clean() -> None:
    fake = FakeController()
    ctrl = Controller(fake.wire(), CFG, BACKOFF, seed=1, shedding=SHED)
    await ctrl.connect()
    try:
        await ctrl.set_streams({Stream.ENCODER: 100})
        assert fake.streams[int(Stream.ENCODER)] == 100
        for _ in range(200):  # a third of the controller's frames lost
            fake._seq += 1
            fake.send_heartbeat()
            fake.send_heartbeat()
            await asyncio.sleep(0.005)
            if fake.streams.get(int(Stream.ENCODER)) == 12:
                break
        assert ctrl.telemetry_scale == SHED.floor
        assert fake.streams == {int(Stream.STATUS): 2, int(Stream.ENCODER): 12}
        await ctrl.set_streams({Stream.HEAD: 40})  # asked for while shedding: scaled too
        assert fake.streams[int(Stream.HEAD)] == 5
        fake.reboot(0xBEEF)  # restored after the reset at the scaled rates
        fake.send_heartbeat(10)
        for _ in range(100):
            await asyncio.sleep(0.02)
            if ctrl.identity is not None and ctrl.identity.boot_id == 0xBEEF:
                break
        assert fake.streams[int(Stream.ENCODER)] == 12
        for _ in range(300):  # clean again: back a step per clean stretch, to the full rates
            fake.send_heartbeat()
            await asyncio.sleep(0.005)
            if ctrl.telemetry_scale == 1.0 and fake.streams.get(int(Stream.HEAD)) == 40:
                break
        assert fake.streams == {
            int(Stream.STATUS): 20,
            int(Stream.ENCODER): 100,
            int(Stream.HEAD): 40,
        }
        assert ctrl.shedder is not None
        assert ctrl.shedder.cuts == 3
    finally:
        await ctrl.close()
        await fake.close()


async def test_start_retries_an_absent_device_and_pushes_each_change_with_its_cause() -> None:
    fake = FakeController()
    transport = fake.wire()
    real_open = transport._open
    failures = [2]

    async def absent_then_present() -> None:
        if failures[0]:
            failures[0] -= 1
            raise FileNotFoundError("no such device /dev/ttyACM0")
        await real_open()

    transport._open = absent_then_present  # type: ignore[method-assign]
    ctrl = Controller(transport, CFG, BACKOFF, seed=1)
    changes: list[tuple[str, str, str]] = []
    ctrl.subscribe(lambda c: changes.append((c.topic, c.snapshot["link"], c.snapshot.link_detail)))
    ctrl.start()  # never raises: an absent controller is a state
    try:
        async with asyncio.timeout(2.0):
            while not ctrl.connected:
                await asyncio.sleep(0.01)
        downs = [detail for topic, link, detail in changes if link == "down"]
        assert downs
        assert all("no such device /dev/ttyACM0" in d for d in downs)  # the cause, not "backoff"
        assert changes[-1][:2] == ("link", "up")
        assert ctrl.link_error == ""
        fake.send_status(State.MOVING, 10, 20)
        await asyncio.sleep(0.01)
        assert changes[-1][:2] == ("state", "up")  # pushed as it arrived
        assert ctrl.snapshot()["state"] == "MOVING"
    finally:
        await ctrl.close()
        await fake.close()


async def test_heartbeat_period_follows_the_controllers_watchdog() -> None:
    # PROTOCOL §9: HEARTBEAT after WATCHDOG_MS / 4 of host silence, read from the controller at
    # connect (it may be in flash) and followed when set; never below the configured interval.
    fake = FakeController()
    fake.params[int(ParamId.WATCHDOG_MS)] = 400
    cfg = SessionConfig(
        heartbeat_interval_s=0.02, dead_after_heartbeats=100, clock_sync_interval_s=0
    )
    ctrl = Controller(fake.wire(), cfg, BACKOFF, seed=1)
    await ctrl.connect()
    try:
        assert ctrl.session.heartbeat_s == pytest.approx(0.1)
        out0 = ctrl.session.stats.heartbeats_out
        await asyncio.sleep(0.55)
        sent = ctrl.session.stats.heartbeats_out - out0
        assert 4 <= sent <= 6, f"{sent} heartbeats in 0.55 s at a 0.1 s period"
        await ctrl.set_param(ParamId.WATCHDOG_MS, 10_000)
        assert ctrl.session.heartbeat_s == pytest.approx(0.25), "a long watchdog is slack"
        await ctrl.set_param(ParamId.WATCHDOG_MS, 40)
        assert ctrl.session.heartbeat_s == pytest.approx(0.02), "never below the configured"
    finally:
        await ctrl.close()
        await fake.close()
