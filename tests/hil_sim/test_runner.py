"""The runner: determinism, telemetry over real frames, clock drift, marks, real-time port."""

from __future__ import annotations

import itertools
import math
import time

import pytest

from firmware.config import TICK_US
from hil_sim.board import RX_RING_BYTES
from hil_sim.client import FrameClient
from hil_sim.runner import MAX_CATCHUP_TICKS, RealtimeRunner, SimLinkPort, Simulation
from hil_sim.scenario import ClockConfig, Scenario, TrackConfig
from protocol import Flag, FrameDecoder, Inputs, Packet, Stream, encode_frame
from protocol.messages import (
    Ack,
    ClockSync,
    ClockSyncReply,
    EncoderSample,
    HeadSample,
    HeadSet,
    Hello,
    Home,
    Identify,
    Jog,
    RangeSample,
    Status,
    StreamSet,
)

REALTIME_TIMEOUT_S = 5.0


def scripted_run(seed: int) -> tuple[bytes, float]:
    """A fixed command script; returns every byte the firmware sent and the final truth."""
    sim = Simulation(Scenario(seed=seed))
    c = FrameClient(sim)
    out = bytearray()
    for msg in (
        Hello(1, 0),
        StreamSet(Stream.ENCODER, 500),
        StreamSet(Stream.HEAD, 50),
        StreamSet(Stream.RANGE, 20),
        HeadSet(300_000, -100_000),
        Home(0),
    ):
        sim.send(encode_frame(msg, c.seq, Flag.ACK_REQUESTED))
        c.seq += 1
        sim.step(5)
        out += sim.receive()
    sim.step(3000)
    out += sim.receive()
    return bytes(out), sim.truth().s_mm


def test_same_seed_same_trace_other_seed_differs() -> None:
    a, sa = scripted_run(4)
    b, sb = scripted_run(4)
    c, _ = scripted_run(5)
    assert a == b
    assert sa == sb
    assert a != c


def test_encoder_stream_rate_seq_and_timestamps() -> None:
    sim = Simulation()
    c = FrameClient(sim)
    assert isinstance(c.request(StreamSet(Stream.ENCODER, 500)), Ack)
    c.received.clear()
    c.run(1000, heartbeat_ms=1000)
    samples = [p for p in c.received if isinstance(p.message, EncoderSample)]
    assert len(samples) == pytest.approx(500, abs=1)
    seqs = [p.seq for p in samples]
    assert all(b - a >= 1 for a, b in itertools.pairwise(seqs))
    times = [m.mcu_time_us for m in c.of_type(EncoderSample)]
    assert {b - a for a, b in itertools.pairwise(times)} == {2000}


def test_index_flag_and_homed_flag_in_encoder_samples() -> None:
    sim = Simulation(Scenario(track=TrackConfig(start_s_mm=400.0)))
    c = FrameClient(sim)
    c.request(StreamSet(Stream.ENCODER, 1000))
    c.request(Home(0))
    c.run(15_000)
    flags = [m.inputs for m in c.of_type(EncoderSample)]
    assert any(f & Inputs.INDEX for f in flags)
    assert any(f & Inputs.HOME for f in flags)
    assert flags[-1] & Inputs.HOMED


def test_head_and_range_streams_follow_the_plant() -> None:
    sim = Simulation()
    c = FrameClient(sim)
    c.request(HeadSet(500_000, 200_000))
    c.request(StreamSet(Stream.HEAD, 100))
    c.request(StreamSet(Stream.RANGE, 50))
    c.run(1000)
    head = c.of_type(HeadSample)[-1]
    assert head.pan_urad == pytest.approx(500_000, abs=200)
    assert head.tilt_urad == pytest.approx(200_000, abs=200)
    rng = c.of_type(RangeSample)[-1]
    expected_um = 4_000_000 / (math.cos(0.5) * math.cos(0.2))
    assert rng.distance_um == pytest.approx(expected_um, abs=10_000)
    assert rng.quality > 0


def test_status_stream_and_clock_drift() -> None:
    sim = Simulation(Scenario(clock=ClockConfig(offset_us=4_294_000_000, drift_ppm=100.0)))
    c = FrameClient(sim)
    c.request(StreamSet(Stream.STATUS, 10))
    c.run(10_000)
    status = c.of_type(Status)
    assert len(status) == pytest.approx(100, abs=1)
    times = [s.mcu_time_us for s in status]
    assert min(times) < 1_000_000 < 4_294_000_000 < max(times), "the µs counter wrapped"
    # A fast crystal: each 1000 µs MCU tick lasts 1 ms / (1 + 100 ppm) of true time.
    assert sim.time_s == pytest.approx(sim.ticks * 1e-3 / (1 + 100e-6), abs=1e-9)
    assert sim.time_s < sim.ticks * 1e-3 - 0.9e-3


def test_reference_marks_are_reported_with_the_encoder_count() -> None:
    sim = Simulation(Scenario(track=TrackConfig(start_s_mm=300.0, reference_marks_mm=(350.0,))))
    c = FrameClient(sim)
    c.request(Jog(100_000, 500_000))
    c.run(1000)
    events = sim.plant.mark_events
    assert len(events) == 1
    assert events[0].mark_s_mm == 350.0
    assert 0.4 < events[0].time_s < 0.8


def test_board_hands_the_rx_ring_over_one_delimiter_at_a_time_with_arrival_stamps() -> None:
    board = Simulation().board
    board.receive_from_host(b"ab\x00cd", 10)
    board.receive_from_host(b"e\x00\x00f", 20)
    board.receive_from_host(b"g", (1 << 32) + 30)
    assert board.link_read() == (b"ab\x00", 10)
    assert board.link_read() == (b"cde\x00", 20)  # completed by the second chunk
    assert board.link_read() == (b"\x00", 20)
    assert board.link_read() == (b"fg", 30)  # no delimiter: the rest, stamped by its last byte
    assert board.link_read() == (b"", 0)
    board.receive_from_host(b"x" * (RX_RING_BYTES - 1), 40)
    board.receive_from_host(b"yz\x00", 50)
    assert board.rx_overruns == 2
    board.system_reset()
    assert board.link_read() == (b"", 0)


def test_realtime_runner_serves_a_port_and_stops_cleanly() -> None:
    port = SimLinkPort()
    got: list[bytes] = []
    port.set_receiver(got.append)
    runner = RealtimeRunner(Simulation(), port=port)
    with runner:
        port.write_to_firmware(encode_frame(Hello(1, 0), 3, Flag.ACK_REQUESTED))
        dec = FrameDecoder()
        deadline = time.monotonic() + REALTIME_TIMEOUT_S
        packets: list[Packet] = []
        while not packets and time.monotonic() < deadline:
            time.sleep(0.01)
            packets = dec.feed(b"".join(got))
        with runner.lock:
            ticks = runner.sim.ticks
    assert packets
    assert isinstance(packets[0].message, Identify)
    assert ticks > 0
    assert runner._thread is None


def test_port_queue_mode_without_receiver() -> None:
    port = SimLinkPort()
    port.deliver(b"ab")
    port.deliver(b"cd")
    assert port.read_from_firmware() == b"abcd"
    assert port.read_from_firmware(timeout_s=0.01) == b""


def test_trolley_pose_follows_the_true_arc_length_on_the_runway() -> None:
    sim = Simulation(Scenario(track=TrackConfig(start_s_mm=2500.0)))
    T = sim.trolley_pose()
    assert T.shape == (4, 4)
    assert T[2, 3] == pytest.approx(4000.0)  # 4 m above the floor
    sim.inject_tooth_skip(1)
    assert sim.trolley_pose()[:3, 3] - T[:3, 3] == pytest.approx([12.7, 0.0, 0.0], abs=1e-6)


def _paced(sim: Simulation) -> tuple[RealtimeRunner, list[tuple[int, bytes]], list[int]]:
    """A runner driven by a fake clock; firmware bytes are logged with the fake time they left,
    host bytes stamped with the fake time they arrived."""
    now = [FAKE_EPOCH_NS]
    port = SimLinkPort(clock_ns=lambda: now[0])
    sent: list[tuple[int, bytes]] = []
    port.set_receiver(lambda data: sent.append((now[0], data)))
    return RealtimeRunner(sim, port=port), sent, now


FAKE_EPOCH_NS = 5_000_000_000_000


def test_a_clock_sync_reply_leaves_within_a_tick_of_its_stamp() -> None:
    sim = Simulation()
    mcu0_us = sim.mcu_time_us
    runner, sent, now = _paced(sim)
    tick_ns = sim.dt_s * 1e9
    runner.run_due(now[0])
    written_ns = 0
    for step in range(1, 41):  # ten ticks, paced in quarter ticks
        now[0] = FAKE_EPOCH_NS + round(step * tick_ns / 4)
        runner.run_due(now[0])
        if step == 21:  # between two ticks: the next tick to run answers it
            written_ns = now[0] + 1
            runner.port.write_to_firmware(encode_frame(ClockSync(token=77), 9))
    replies = [
        (left_ns, p.message)
        for left_ns, data in sent
        for p in FrameDecoder().feed(data)
        if isinstance(p.message, ClockSyncReply)
    ]
    assert len(replies) == 1
    left_ns, reply = replies[0]
    # The stamp's tick was due at this host time (ticks are paced from the epoch).
    stamp_ns = FAKE_EPOCH_NS + (reply.mcu_time_us - mcu0_us) // TICK_US * tick_ns
    assert reply.token == 77
    assert written_ns < stamp_ns <= left_ns
    # A reply leaving a tick after its stamp biases the host's clock mapping by that much.
    assert left_ns - stamp_ns < tick_ns / 4 + 1


def test_bytes_arriving_between_ticks_are_stamped_with_their_arrival_not_the_tick() -> None:
    sim = Simulation()  # a 20 ppm fast crystal
    mcu0_us = sim.mcu_time_us
    runner, sent, now = _paced(sim)
    tick_ns = sim.dt_s * 1e9
    runner.run_due(now[0])
    arrivals: dict[int, int] = {}
    for step in range(1, 46):  # four and a half ticks, paced in tenths of a tick
        now[0] = FAKE_EPOCH_NS + round(step * tick_ns / 10)
        if step in (23, 27):  # two probes between the same two ticks, and one a tick later
            arrivals[step] = now[0]
            runner.port.write_to_firmware(encode_frame(ClockSync(token=step), step))
        runner.run_due(now[0])
        if step == 34:
            arrivals[step] = now[0]
            runner.port.write_to_firmware(encode_frame(ClockSync(token=step), step))
    replies = {
        p.message.token: p.message
        for _, data in sent
        for p in FrameDecoder().feed(data)
        if isinstance(p.message, ClockSyncReply)
    }
    assert set(replies) == set(arrivals)
    for token, at_ns in arrivals.items():
        reply = replies[token]
        # The counter at the arrival: elapsed host time at the crystal's rate.
        expected_us = mcu0_us + (at_ns - FAKE_EPOCH_NS) / 1000 * (1 + 20e-6)
        assert abs(reply.rx_time_us - expected_us) <= 1
        assert reply.rx_time_us < reply.mcu_time_us  # read at the next tick
        assert reply.mcu_time_us - reply.rx_time_us < TICK_US
    assert replies[23].mcu_time_us == replies[27].mcu_time_us
    assert replies[27].rx_time_us - replies[23].rx_time_us == pytest.approx(TICK_US * 0.4, abs=1)


def test_run_due_runs_the_tick_due_now_and_bounds_the_catch_up() -> None:
    sim = Simulation()
    runner, _, now = _paced(sim)
    tick_ns = sim.dt_s * 1e9
    assert runner.run_due(now[0]) == pytest.approx(tick_ns, abs=1)
    assert sim.ticks == 1  # tick 0 is due at the epoch itself
    assert runner.run_due(now[0] + round(tick_ns) - 10) == pytest.approx(10, abs=1)
    assert sim.ticks == 1
    wait_ns = runner.run_due(now[0] + round(500.5 * tick_ns))
    assert sim.ticks == 1 + MAX_CATCHUP_TICKS
    assert runner.late_ticks == 500 - 1
    assert wait_ns < 0  # behind: the thread runs the rest without sleeping


def test_bytes_arriving_after_a_late_tick_was_due_wait_for_the_next_tick() -> None:
    sim = Simulation()
    runner, sent, now = _paced(sim)
    tick_ns = sim.dt_s * 1e9
    runner.run_due(now[0])
    # Tick 1 is due at 1.0 ticks; the probe arrives at 1.2 and the thread only wakes at 1.3.
    now[0] = FAKE_EPOCH_NS + round(1.2 * tick_ns)
    runner.port.write_to_firmware(encode_frame(ClockSync(token=5), 3))
    now[0] = FAKE_EPOCH_NS + round(1.3 * tick_ns)
    runner.run_due(now[0])
    assert not sent  # in plant time the probe came after tick 1: tick 2 answers it
    now[0] = FAKE_EPOCH_NS + round(2.05 * tick_ns)
    runner.run_due(now[0])
    replies = [
        p.message
        for _, data in sent
        for p in FrameDecoder().feed(data)
        if isinstance(p.message, ClockSyncReply)
    ]
    assert len(replies) == 1
    held_us = replies[0].mcu_time_us - replies[0].rx_time_us
    assert held_us == pytest.approx(0.8 * TICK_US, abs=2)  # stamped as it came, read at tick 2


def test_the_plant_tells_its_pose_between_ticks_from_its_history() -> None:
    sim = Simulation(Scenario(seed=3))
    c = FrameClient(sim)
    sim.plant.keep_history(200)
    for msg in (HeadSet(400_000, -200_000), Jog(300_000, 1_000_000)):
        sim.send(encode_frame(msg, c.seq, Flag.ACK_REQUESTED))
        c.seq += 1
        sim.step(5)
    before = []
    for _ in range(300):  # moving and slewing: the pose changes every tick
        before.append(sim.truth())
        sim.step(1)
    a, b = before[-3], before[-2]
    assert b.s_mm != a.s_mm
    assert b.pan_rad != a.pan_rad
    mid = sim.truth_at((a.time_s + b.time_s) / 2)
    assert mid is not None
    assert mid.s_mm == pytest.approx((a.s_mm + b.s_mm) / 2, abs=1e-9)
    assert mid.pan_rad == pytest.approx((a.pan_rad + b.pan_rad) / 2, abs=1e-12)
    assert mid.tilt_rad == pytest.approx((a.tilt_rad + b.tilt_rad) / 2, abs=1e-12)
    exact = sim.truth_at(a.time_s)
    assert exact is not None
    assert exact.s_mm == a.s_mm
    assert sim.truth_at(before[0].time_s) is None  # older than the 200 ticks kept
    assert sim.truth_at(sim.time_s + 0.01) is None  # not yet happened
    assert Simulation(Scenario()).truth_at(0.0) is None  # no history unless asked for
