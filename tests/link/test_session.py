"""Session: handshake, retransmission, duplicates, RTO, window, NAK, heartbeat, statistics."""

from __future__ import annotations

import asyncio
import itertools
import struct
from collections.abc import AsyncIterator

import pytest

from host.link.common import (
    CommandTimeout,
    ControllerRejected,
    LinkDown,
    LinkEvent,
    ProtocolMismatch,
)
from host.link.session import RtoEstimator, Session, SessionConfig
from host.transport.base import TransportError
from host.transport.memory import Impairment
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, FrameDecoder, cobs, encode_frame
from protocol.compat import encode_v1
from protocol.crc import frame_crc
from protocol.enums import NakCode, State
from protocol.messages import (
    Ack,
    ClockSync,
    ClockSyncReply,
    HeadSet,
    Identify,
    ParamGet,
    ParamSet,
    ParamValue,
    Stop,
)
from tests.link.fake_controller import FakeController

FAST = SessionConfig(rto_initial_s=0.02, rto_min_s=0.02, rto_max_s=0.2, max_tries=12)


async def start(fake: FakeController, config: SessionConfig = FAST, **wire: Impairment) -> Session:
    """An open transport to the fake and a started session on it."""
    transport = fake.wire(**wire)
    await transport.open()
    session = Session(transport, config)
    session.start()
    return session


@pytest.fixture
async def fake() -> AsyncIterator[FakeController]:
    ctrl = FakeController()
    yield ctrl
    await ctrl.close()
    if ctrl.transport is not None:
        await ctrl.transport.close()


async def test_handshake_returns_identity(fake: FakeController) -> None:
    session = await start(fake)
    ident, rebooted = await session.handshake()
    await session.stop()
    assert (ident.boot_id, ident.rx_window, rebooted) == (0x1234, 4, False)
    assert session.stats.handshakes == 1


@pytest.mark.parametrize(
    ("version", "schema"), [(PROTOCOL_VERSION + 1, SCHEMA_HASH), (PROTOCOL_VERSION, 0xDEADBEEF)]
)
async def test_handshake_mismatch_names_both_sides(
    fake: FakeController, version: int, schema: int
) -> None:
    fake.protocol_version, fake.schema_hash = version, schema
    session = await start(fake)
    with pytest.raises(ProtocolMismatch) as info:
        await session.handshake()
    await session.stop()
    text = str(info.value)
    assert f"version {PROTOCOL_VERSION}" in text
    assert f"version {version}" in text
    assert f"0x{SCHEMA_HASH:08X}" in text
    assert f"0x{schema:08X}" in text


async def test_new_boot_id_on_rehandshake_is_a_reset(fake: FakeController) -> None:
    session = await start(fake)
    await session.handshake()
    fake.reboot(0x9999)
    ident, rebooted = await session.handshake()
    await session.stop()
    assert rebooted
    assert ident.boot_id == 0x9999
    assert session.stats.controller_resets == 1


async def test_no_command_lost_or_repeated_under_ten_percent_loss(fake: FakeController) -> None:
    lossy = Impairment(loss=0.1)
    cfg = SessionConfig(rto_initial_s=0.01, rto_min_s=0.005, rto_max_s=0.05, max_tries=30)
    session = await start(fake, cfg, tx=lossy, rx=lossy)
    await session.handshake()
    count = 1000
    replies = await asyncio.gather(
        *(session.request(ParamSet(param_id=2, value=i)) for i in range(count))
    )
    await session.stop()
    assert len(replies) == count
    assert sum(fake.executions.values()) == count  # each executed exactly once
    assert max(fake.executions.values()) == 1
    assert {r.message.value for r in replies} == set(range(count))  # type: ignore[attr-defined]
    stats = session.stats
    assert stats.retransmits > 0
    assert stats.timeouts == 0
    total_lost = fake.transport.tx.stats.lost + fake.transport.rx.stats.lost  # type: ignore[union-attr]
    assert stats.retransmits <= total_lost * 2 + 50


async def test_late_duplicate_reply_is_counted_and_ignored(fake: FakeController) -> None:
    session = await start(fake)
    await session.handshake()
    reply = await session.request(Stop())
    fake.send(Ack(reply.message.req_seq, int(State.READY)))  # type: ignore[attr-defined]
    fake.send(Ack(reply.message.req_seq, int(State.READY)))  # type: ignore[attr-defined]
    await asyncio.sleep(0.01)
    await session.stop()
    assert session.stats.duplicate_replies == 2


async def test_duplicated_frames_do_not_execute_twice(fake: FakeController) -> None:
    dup = Impairment(duplicate=0.5)
    session = await start(fake, tx=dup, rx=dup)
    await session.handshake()
    for i in range(100):
        await session.request(ParamSet(param_id=2, value=i))
    await asyncio.sleep(0.01)
    await session.stop()
    assert sum(fake.executions.values()) == 100
    host_dups = fake.transport.rx.stats.duplicated  # type: ignore[union-attr]
    assert session.stats.duplicate_replies + session.stats.rx_out_of_order >= host_dups // 2


async def test_rto_adapts_to_the_link_rtt(fake: FakeController) -> None:
    slow = Impairment(delay_s=0.03)
    session = await start(fake, SessionConfig(rto_initial_s=0.5), tx=slow, rx=slow)
    await session.handshake()
    for _ in range(20):
        await session.request(Stop())
    await session.stop()
    rtt = session.stats.rtt
    # HELLO and 20 STOPs, less any that a stall of this machine made go out twice (Karn's rule).
    assert rtt.samples == 21 - session.stats.retransmits
    assert rtt.srtt_s is not None
    assert 0.055 < rtt.srtt_s < 0.12  # loose above: a loaded CI machine adds latency
    assert rtt.min_s is not None
    assert rtt.min_s >= 0.059
    assert 0.06 < session.rto.rto_s < 0.2  # shrank from 0.5 towards the measured RTT
    # The RTO keeps a 5 ms floor above SRTT, so the scheduler's jitter alone retransmits rarely.
    assert session.stats.retransmits <= 1


async def test_karn_no_sample_from_retransmitted_command(fake: FakeController) -> None:
    session = await start(fake, SessionConfig(rto_initial_s=0.05, rto_min_s=0.05))
    await session.handshake()
    samples = session.stats.rtt.samples
    fake.silent = True
    task = asyncio.create_task(session.request(Stop()))
    await asyncio.sleep(0.07)
    fake.silent = False
    await task
    await session.stop()
    assert session.stats.retransmits >= 1
    assert session.stats.rtt.samples == samples


async def test_gives_up_after_max_tries_with_backoff(fake: FakeController) -> None:
    cfg = SessionConfig(rto_initial_s=0.02, rto_min_s=0.02, rto_max_s=0.08, max_tries=5)
    session = await start(fake, cfg)
    await session.handshake()
    fake.silent = True
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    with pytest.raises(CommandTimeout, match="STOP"):
        await session.request(Stop())
    elapsed = loop.time() - t0
    await session.stop()
    assert session.stats.timeouts == 1
    assert session.stats.retransmits == 4
    assert 0.02 + 0.04 + 0.08 * 3 <= elapsed < 1.0  # 20, 40, 80, 80, 80 ms: doubling, capped


async def test_commands_timing_out_together_back_off_the_shared_rto_once(
    fake: FakeController,
) -> None:
    """Four commands lost at once are one loss episode: the RTO new commands start with doubles
    per round of retransmissions, not per command (it used to reach rto_max_s at once)."""
    cfg = SessionConfig(rto_initial_s=0.02, rto_min_s=0.02, rto_max_s=2.0, max_tries=3)
    session = await start(fake, cfg)
    await session.handshake()  # one RTT sample on a lossless memory wire: the RTO floor
    base = session.rto.rto_s
    fake.silent = True
    results = await asyncio.gather(
        *(session.request(ParamSet(param_id=2, value=i)) for i in range(4)),
        return_exceptions=True,
    )
    await session.stop()
    assert all(isinstance(r, CommandTimeout) for r in results)
    assert session.stats.retransmits == 4 * 2
    # Two rounds of retransmissions: the shared RTO doubled twice (eight doublings before).
    assert session.rto.rto_s == pytest.approx(base * 4)


def test_forgetting_the_backoff_returns_to_the_measured_rto() -> None:
    """What a rebooted controller left unanswered does not slow the next handshake."""
    rto = RtoEstimator(SessionConfig(rto_initial_s=0.5, rto_min_s=0.02, rto_max_s=2.0))
    rto.forget_backoff()
    assert rto.rto_s == 0.5  # no sample yet: the configured start
    rto.sample(0.03)
    measured = rto.rto_s
    for _ in range(5):
        rto.backoff()
    assert rto.rto_s == 2.0
    rto.forget_backoff()
    assert rto.rto_s == measured


async def test_window_is_respected(fake: FakeController) -> None:
    fake.rx_window = 6
    fake.reply_delay_s = 0.02
    # A high RTO floor: a retransmission under CI load would add a duplicate delayed reply,
    # which the fake would count as one more command in flight.
    session = await start(fake, SessionConfig(rto_initial_s=1.0, rto_min_s=0.5))
    await session.handshake()
    # Not STOP: stops bypass the window (they run on arrival, PROTOCOL §6).
    await asyncio.gather(*(session.request(HeadSet(0, 0)) for _ in range(20)))
    await session.stop()
    assert fake.max_inflight_seen == 6  # (2 · rx_window + 1) // 2: see Session._window_open


async def test_nak_raises_with_code_and_state(fake: FakeController) -> None:
    session = await start(fake)
    await session.handshake()
    fake.nak_next = (NakCode.NOT_HOMED, State.IDLE)
    with pytest.raises(ControllerRejected) as info:
        await session.request(Stop())
    await session.stop()
    assert info.value.code is NakCode.NOT_HOMED
    assert info.value.state is State.IDLE
    assert session.stats.naks == 1


async def test_cancelled_request_frees_its_slot(fake: FakeController) -> None:
    fake.rx_window = 1
    session = await start(fake)
    await session.handshake()
    fake.silent = True
    task = asyncio.create_task(session.request(Stop()))
    await asyncio.sleep(0.01)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    fake.silent = False
    await asyncio.wait_for(session.request(Stop()), 1.0)
    await session.stop()


async def test_halt_fails_pending_with_link_down(fake: FakeController) -> None:
    session = await start(fake)
    await session.handshake()
    fake.silent = True
    task = asyncio.create_task(session.request(Stop()))
    await asyncio.sleep(0.01)
    await session.stop("unplugged")
    with pytest.raises(LinkDown, match="unplugged"):
        await task
    with pytest.raises(LinkDown):
        await session.request(Stop())


async def test_heartbeat_sent_when_idle_and_silence_declared(fake: FakeController) -> None:
    events: list[LinkEvent] = []
    cfg = SessionConfig(heartbeat_interval_s=0.02, dead_after_heartbeats=5, clock_sync_interval_s=0)
    session = await start(fake, cfg)
    session.on_event = lambda ev, _detail: events.append(ev)
    await session.handshake()
    fake.silent = True
    await asyncio.sleep(0.2)
    await session.stop()
    assert session.stats.heartbeats_out >= 3
    assert events == [LinkEvent.HEARTBEAT_TIMEOUT]


async def test_uptime_regression_reports_controller_reset(fake: FakeController) -> None:
    events: list[LinkEvent] = []
    session = await start(fake)
    session.on_event = lambda ev, _detail: events.append(ev)
    await session.handshake()
    fake.send_heartbeat(5000)
    fake.send_heartbeat(100)
    fake.reboot(0x4321)
    fake.send_heartbeat(100)
    await asyncio.sleep(0.01)
    await session.stop()
    assert events == [LinkEvent.RESET_SUSPECTED]
    assert session.stats.heartbeats_in == 3


async def test_stats_match_injected_telemetry_loss(fake: FakeController) -> None:
    received: list[object] = []
    lossy = Impairment(loss=0.2)
    session = await start(fake, SessionConfig(clock_sync_interval_s=0), rx=lossy)
    session.on_packet = lambda p: received.append(p.message)
    fake.send_encoder(0, 0)  # anchors the seq tracking (may itself be lost: then the next one)
    for i in range(1, 500):
        fake.send_encoder(i * 1000, i)
    fake.transport.rx.impairment = Impairment()  # type: ignore[union-attr]
    fake.send_encoder(999_000, 999)  # a last one that surely arrives closes every gap
    await asyncio.sleep(0.02)
    await session.stop()
    lost = fake.transport.rx.stats.lost  # type: ignore[union-attr]
    first_lost = 0 if received and received[0].encoder_count == 0 else 1  # type: ignore[attr-defined]
    assert session.stats.rx_lost == lost - first_lost
    assert session.stats.frames_in == len(received) == 501 - lost
    assert session.stats.drops.total() == 0


async def test_corrupt_bytes_are_counted_not_fatal(fake: FakeController) -> None:
    session = await start(fake)
    await session.handshake()
    fake.transport.inject(b"\x05garbage\x00\x01\x02\x00")  # type: ignore[union-attr]
    await session.request(Stop())
    await session.stop()
    assert session.stats.drops.total() == 2


async def test_controller_seq_restart_is_reported(fake: FakeController) -> None:
    events: list[LinkEvent] = []
    session = await start(fake, SessionConfig(clock_sync_interval_s=0))
    session.on_event = lambda ev, _detail: events.append(ev)
    for i in range(400):
        fake.send_encoder(i, i)
    fake.reboot(0x4321)  # its seq starts again at 0
    fake.send_encoder(0, 0)
    await asyncio.sleep(0.01)
    await session.stop()
    assert events == [LinkEvent.RESET_SUSPECTED]
    assert session.stats.rx_lost == 0


async def test_clock_probes_go_out_zero_padded_and_as_long_as_their_replies(
    fake: FakeController, monkeypatch: pytest.MonkeyPatch
) -> None:
    host_bytes: list[bytes] = []
    answer = fake.receive

    def tap(data: bytes) -> None:
        host_bytes.append(bytes(data))
        answer(data)

    monkeypatch.setattr(fake, "receive", tap)  # before wire(): the transport delivers here
    session = await start(fake, SessionConfig(clock_sync_interval_s=0.005))
    await session.handshake()
    for _ in range(200):
        if session.stats.clock_replies >= 3:
            break
        await asyncio.sleep(0.005)
    await session.stop()
    assert session.stats.clock_replies >= 3
    probes = []
    for part in b"".join(host_bytes).split(b"\x00"):
        frame = part + b"\x00"
        packets = FrameDecoder().feed(frame) if part else []
        if packets and isinstance(packets[0].message, ClockSync):
            probes.append((len(frame), packets[0].message))
    assert len(probes) >= 3
    reply = ClockSyncReply(0xFFFF, 0xFFFF_FFFF, 0xFFFF_FFFF, 0xFFFF_FFFF)
    reply_len = len(encode_frame(reply, 0xFFFF))
    for length, probe in probes:
        assert length == reply_len
        assert (probe.padding0, probe.padding1, probe.padding2) == (0, 0, 0)


async def test_clock_probe_waits_until_the_host_has_been_quiet(
    fake: FakeController, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The heartbeat loop wakes at the probe rate. A probe written right behind a heartbeat would
    # wait for it on a serial line: a delay on the way out only, which clock sync takes for
    # asymmetry (it mapped every stamp ~0.5 ms early over the emulated 115200 Bd line).
    cfg = SessionConfig(
        heartbeat_interval_s=0.02, clock_sync_interval_s=0.02, clock_probe_quiet_s=0.008
    )
    session = await start(fake, cfg)
    writes: list[tuple[float, bytes]] = []
    send = session.transport.send

    def stamped(frame: bytes) -> None:
        writes.append((asyncio.get_running_loop().time(), bytes(frame)))
        send(frame)

    monkeypatch.setattr(session.transport, "send", stamped)
    await session.handshake()
    await asyncio.sleep(0.4)
    await session.stop()
    probes = 0
    for (before, _), (at, frame) in itertools.pairwise(writes):
        packets = FrameDecoder().feed(frame)
        if packets and isinstance(packets[0].message, ClockSync):
            probes += 1
            assert at - before >= cfg.clock_probe_quiet_s - 1e-6
    assert probes >= 5
    assert session.stats.clock_replies >= 5


async def test_a_retransmission_whose_send_loses_the_link_fails_the_command_once(
    fake: FakeController,
) -> None:
    """A transport may report the loss (halting the session) from inside send(), then raise."""
    session = await start(fake)
    fake.silent = True
    loop = asyncio.get_running_loop()
    errors: list[dict[str, object]] = []
    loop.set_exception_handler(lambda _loop, ctx: errors.append(ctx))
    real_send = session.transport.send
    sends = 0

    def send_then_die(frame: bytes) -> None:
        nonlocal sends
        sends += 1
        if sends < 2:
            real_send(frame)
            return
        session.halt("serial port vanished")  # what the transport's on_lost leads to
        raise TransportError("write failed")

    session.transport.send = send_then_die  # type: ignore[method-assign]
    try:
        with pytest.raises(LinkDown, match="vanished"):
            await session.request(Stop())
        await asyncio.sleep(0.05)
    finally:
        loop.set_exception_handler(None)
    assert errors == []


# ---- a newer controller: unknown codes, states, flags and ids (PROTOCOL.md §2) -----------


def _raw_wire(msg_id: int, payload: bytes, seq: int = 900, flags: int = 0) -> bytes:
    """A well-framed controller frame with any id and payload (beyond what our encoder allows)."""
    raw = struct.pack("<BBHB", PROTOCOL_VERSION, flags, seq, msg_id) + payload
    return cobs.encode(raw + frame_crc(raw).to_bytes(2, "big")) + b"\x00"


async def test_unknown_nak_code_fails_the_command_at_once_with_its_number(
    fake: FakeController, caplog: pytest.LogCaptureFixture
) -> None:
    session = await start(fake, SessionConfig(rto_initial_s=1.0, rto_min_s=1.0))
    await session.handshake()
    fake.silent = True
    task = asyncio.create_task(session.request(ParamGet(1)))
    await asyncio.sleep(0.02)
    (seq,) = session._inflight
    assert fake.transport is not None
    t0 = asyncio.get_running_loop().time()
    fake.transport.inject(_raw_wire(0x82, struct.pack("<HBB", seq, 200, 77)))
    with pytest.raises(ControllerRejected) as info:
        await task
    waited_s = asyncio.get_running_loop().time() - t0
    await session.stop()
    assert waited_s < 0.5, "failed at once, not after the retransmissions"
    assert (info.value.code, info.value.state) == (200, 77)
    assert "rejected: 200 in state 77" in str(info.value)
    assert "unknown NAK code 200" in caplog.text


async def test_unknown_ids_flags_and_reserved_values_never_break_the_session(
    fake: FakeController, caplog: pytest.LogCaptureFixture
) -> None:
    session = await start(fake)
    await session.handshake()
    assert fake.transport is not None
    for _ in range(3):  # logged once each, however often they come
        fake.transport.inject(_raw_wire(0xEE, b"\x01\x02\x03"))  # an id from a newer schema
        fake.transport.inject(_raw_wire(0x02, struct.pack("<I", 5), flags=0xF0))  # HEARTBEAT
    reply = await session.request(ParamSet(1, 700))  # the session still works
    await session.stop()
    assert reply.message == ParamValue(reply.message.req_seq, 1, 700)  # type: ignore[attr-defined]
    assert session._decoder.drops.unknown_id == 3
    assert caplog.text.count("unknown message id 238") == 1
    assert caplog.text.count("unknown header flag bits 240") == 1


async def test_a_version_1_controller_is_refused_with_its_version_shown(
    fake: FakeController,
) -> None:
    # A v1 controller frames IDENTIFY with the old CRC and without capabilities: still read.
    session = await start(fake)
    fake.silent = True
    task = asyncio.create_task(session.handshake())
    await asyncio.sleep(0.02)
    (seq,) = session._inflight
    ident = Identify(seq, 1, 0x1A2B3C4D, 0x000200, 9, 4000, 3200, 20, 12_700, 10**6, 84, 8, 1)
    assert fake.transport is not None
    fake.transport.inject(encode_v1(ident, 0, 0))
    with pytest.raises(ProtocolMismatch) as info:
        await task
    await session.stop()
    assert "controller speaks version 1 schema 0x1A2B3C4D" in str(info.value)
