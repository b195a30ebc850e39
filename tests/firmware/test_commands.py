"""Command handling through real frames: handshake, NAKs, duplicates, state rules."""

from __future__ import annotations

import struct

import pytest

from firmware import config
from hil_sim.client import FrameClient
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, Flag, NakCode, ParamId, State, encode_frame
from protocol.cobs import encode as cobs_encode
from protocol.crc import frame_crc
from protocol.messages import (
    Ack,
    ClearFault,
    ClockSync,
    ClockSyncReply,
    Estop,
    HeadSet,
    Hello,
    Home,
    Identify,
    Jog,
    MoveTo,
    Nak,
    ParamGet,
    ParamSet,
    ParamValue,
    StreamSet,
)
from tests.firmware.conftest import Rig


def raw_frame(msg_id: int, payload: bytes, seq: int, flags: int = Flag.ACK_REQUESTED) -> bytes:
    """A well-framed frame with any id and payload (the codec would refuse to build some)."""
    raw = struct.pack("<BBHB", PROTOCOL_VERSION, flags, seq, msg_id) + payload
    return cobs_encode(raw + frame_crc(raw).to_bytes(2, "big")) + b"\x00"


def take_seq(client: FrameClient) -> int:
    """The next command seq, spent (commands run in seq order: a hand-made frame takes its turn)."""
    seq = client.seq
    client.seq = (seq + 1) & 0xFFFF
    return seq


def wait_reply(client: FrameClient, seq: int) -> object:
    """Step until the reply to seq."""
    return client.wait_reply(seq, max_ticks=20)


def test_hello_answers_identify_with_the_rig_constants(rig: Rig) -> None:
    seq = rig.client.send(Hello(1, 0xDEAD))
    reply = rig.client.wait_reply(seq)
    assert isinstance(reply, Identify)
    assert reply.req_seq == seq
    assert (reply.encoder_counts_per_rev, reply.steps_per_rev) == (4000, 3200)
    assert (reply.sprocket_teeth, reply.chain_pitch_um) == (20, 12_700)
    assert (reply.mcu_clock_hz, reply.max_frame, reply.rx_window) == (1_000_000, 84, 8)
    assert reply.schema_hash == SCHEMA_HASH
    assert reply.fw_version == config.FW_VERSION
    assert reply.state == State.IDLE


def test_unknown_id_with_ack_requested_is_nakked(rig: Rig) -> None:
    seq = take_seq(rig.client)
    rig.sim.send(raw_frame(0x7E, b"\x01\x02", seq=seq))
    reply = wait_reply(rig.client, seq)
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.UNKNOWN_MESSAGE


def test_unknown_id_without_ack_request_is_silently_counted(rig: Rig) -> None:
    rig.sim.send(raw_frame(0x7E, b"", seq=41, flags=Flag.NONE))
    rig.client.run(5, heartbeat_ms=1000)
    assert not [p for p in rig.client.received if getattr(p.message, "req_seq", None) == 41]
    assert rig.sim.firmware.counters.frames_in >= 1


def test_controller_to_host_id_is_not_a_command(rig: Rig) -> None:
    seq = take_seq(rig.client)
    rig.sim.send(encode_frame(Ack(1, 1), seq=seq, flags=Flag.ACK_REQUESTED))
    reply = wait_reply(rig.client, seq)
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.UNKNOWN_MESSAGE


def test_bad_payload_length_is_nakked_and_changes_nothing(rig: Rig) -> None:
    seq = take_seq(rig.client)
    rig.sim.send(raw_frame(0x31, struct.pack("<H", int(ParamId.WATCHDOG_MS)), seq=seq))
    reply = wait_reply(rig.client, seq)
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.BAD_PAYLOAD
    assert rig.sim.firmware.params.get(ParamId.WATCHDOG_MS) == 500


@pytest.mark.parametrize(
    "msg",
    [
        StreamSet(9, 10),  # stream beyond the enum
        StreamSet(0, 1001),  # rate above 1 kHz
        Jog(3_000_000, 1000),  # velocity beyond MAX_SPEED
        MoveTo(1000, 0, 1000),  # zero speed
        HeadSet(4_000_000, 0),  # pan beyond half a turn
    ],
)
def test_out_of_range_fields_are_nakked(rig: Rig, msg: object) -> None:
    # The codec refuses to encode these, so build the frame from raw fields.
    from protocol import spec_of

    spec = spec_of(msg)
    values = [getattr(msg, f.name) for f in spec.fields]
    payload = struct.pack(spec.struct_format, *values)
    seq = take_seq(rig.client)
    rig.sim.send(raw_frame(spec.id, payload, seq=seq))
    reply = wait_reply(rig.client, seq)
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.OUT_OF_RANGE
    assert rig.sim.firmware.state is State.IDLE
    assert rig.sim.firmware.active_streams == []


def test_param_set_out_of_range_and_unknown(rig: Rig) -> None:
    reply = rig.client.request(ParamSet(ParamId.WATCHDOG_MS, 10))
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.OUT_OF_RANGE
    reply = rig.client.request(ParamGet(999))
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.UNKNOWN_PARAM
    reply = rig.client.request(ParamSet(ParamId.SOFT_LIMIT_MIN_UM, 90_000_000))
    assert isinstance(reply, Nak), "min above max must be refused"
    reply = rig.client.request(ParamSet(ParamId.WATCHDOG_MS, 800))
    assert isinstance(reply, ParamValue)
    assert reply.value == 800
    assert rig.client.request(ParamGet(ParamId.WATCHDOG_MS)) == ParamValue(
        reply.req_seq + 1, 1, 800
    )


def test_move_before_homing_is_not_homed(rig: Rig) -> None:
    reply = rig.client.request(MoveTo(100_000, 100_000, 100_000))
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.NOT_HOMED
    assert reply.state == State.IDLE


def test_motion_in_estop_is_bad_state_naming_the_state(homed: Rig) -> None:
    c = homed.client
    assert isinstance(c.request(Estop()), Ack)
    for msg in (MoveTo(100_000, 100_000, 100_000), Jog(10_000, 10_000), Home(0), HeadSet(0, 0)):
        reply = c.request(msg)
        assert isinstance(reply, Nak), msg
        assert (reply.code, reply.state) == (NakCode.BAD_STATE, State.ESTOP)
    reply = c.request(ClearFault())
    assert isinstance(reply, Ack)
    assert reply.state == State.IDLE  # the drive was off: the reference is lost, home again


def test_home_while_homing_is_bad_state(rig: Rig) -> None:
    assert isinstance(rig.client.request(Home(0)), Ack)
    reply = rig.client.request(Home(0))
    assert isinstance(reply, Nak)
    assert (reply.code, reply.state) == (NakCode.BAD_STATE, State.HOMING)


def test_move_beyond_soft_limit_is_refused(homed: Rig) -> None:
    reply = homed.client.request(MoveTo(-1_000, 100_000, 100_000))
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.BEYOND_LIMIT
    assert homed.sim.firmware.state is State.READY


def test_duplicate_is_answered_from_cache_not_executed(homed: Rig) -> None:
    c = homed.client
    seq = c.send(MoveTo(200_000, 200_000, 500_000))
    first = c.wait_reply(seq)
    c.run(3000)
    assert homed.sim.firmware.state is State.READY
    pos = homed.sim.firmware.position_um
    # Retransmission of the same frame after it completed: same answer, no second motion.
    c.send(MoveTo(200_000, 200_000, 500_000), flags=Flag.ACK_REQUESTED | Flag.RETRANSMIT, seq=seq)
    again = c.wait_reply(seq)
    assert again == first
    assert homed.sim.firmware.counters.duplicates == 1
    assert homed.sim.firmware.state is State.READY
    # Other content under a remembered seq is not a repeat and not new: refused, nothing runs.
    c.send(MoveTo(100_000, 200_000, 500_000), seq=seq)
    refused = c.wait_reply(seq)
    assert isinstance(refused, Nak)
    assert refused.code == NakCode.STALE_SEQ
    c.run(500)
    assert homed.sim.firmware.state is State.READY
    assert abs(homed.sim.firmware.position_um - pos) < 50
    assert abs(pos - 200_000) < 200


def test_clock_sync_reply_carries_mcu_time(rig: Rig) -> None:
    seq = rig.client.send(ClockSync(0xABCD))
    reply = rig.client.wait_reply(seq)
    assert isinstance(reply, ClockSyncReply)
    assert reply.token == 0xABCD
    assert abs(reply.mcu_time_us - rig.sim.mcu_time_us) <= 2 * config.TICK_US


def test_clock_sync_padding_is_ignored_whatever_its_value(rig: Rig) -> None:
    # Senders send zeros, but a receiver must not refuse other values (a later version may
    # use those bytes): the probe is answered as usual.
    seq = rig.client.send(ClockSync(0x5A5A, 0xFFFF, 0xFFFF_FFFF, 0xFFFF_FFFF))
    reply = rig.client.wait_reply(seq)
    assert isinstance(reply, ClockSyncReply)
    assert reply.token == 0x5A5A
    assert abs(reply.mcu_time_us - rig.sim.mcu_time_us) <= 2 * config.TICK_US


def _clock_replies(rig: Rig, ticks: int) -> dict[int, ClockSyncReply]:
    """Step, collecting clock-sync replies by token."""
    rig.client.run(ticks)
    return {m.token: m for m in rig.client.of_type(ClockSyncReply)}


def test_clock_sync_reply_stamps_each_probe_with_its_arrival_between_ticks(rig: Rig) -> None:
    # Two probes arrive at different moments between two ticks; the tick answers both, each
    # with the µs time its delimiter arrived (as the RX interrupt captures it) and the tick's.
    sim = rig.sim
    sim.step(3)
    tick_us = sim.mcu_time_us + config.TICK_US  # the tick that will run next
    now_s = sim.time_s
    early_s, late_s = now_s - 0.0008, now_s - 0.00025
    sim.send(encode_frame(ClockSync(1), 100), at_s=early_s)
    sim.send(encode_frame(ClockSync(2), 101), at_s=late_s)
    replies = _clock_replies(rig, 1)
    assert set(replies) == {1, 2}
    for token, at_s, held_us in ((1, early_s, 800), (2, late_s, 250)):
        reply = replies[token]
        assert reply.mcu_time_us == tick_us & 0xFFFF_FFFF
        assert reply.rx_time_us == sim.board.mcu_us_at(at_s) & 0xFFFF_FFFF
        # 20 ppm fast crystal: the counter gains 0.02 µs per ms of true time.
        assert reply.mcu_time_us - reply.rx_time_us in (held_us, held_us + 1)


def test_clock_sync_arrival_is_the_delimiter_of_a_probe_split_across_ticks(rig: Rig) -> None:
    sim = rig.sim
    frame = encode_frame(ClockSync(3), 102)
    sim.send(frame[:5], at_s=sim.time_s - 0.0005)
    sim.step(2)  # the firmware reads the first bytes; the frame is not complete
    delimiter_s = sim.time_s - 0.0001
    sim.send(frame[5:] + encode_frame(ClockSync(4), 103)[:3], at_s=delimiter_s)
    reply = _clock_replies(rig, 1)[3]
    assert reply.rx_time_us == sim.board.mcu_us_at(delimiter_s) & 0xFFFF_FFFF
    assert reply.rx_time_us < reply.mcu_time_us


def test_clock_sync_probe_read_at_a_tick_arrived_at_its_time(rig: Rig) -> None:
    # Sent between steps in lockstep, a probe arrives at the instant the next tick runs.
    seq = rig.client.send(ClockSync(0x77))
    reply = rig.client.wait_reply(seq)
    assert isinstance(reply, ClockSyncReply)
    assert reply.rx_time_us == reply.mcu_time_us


def test_garbage_bytes_are_counted_not_fatal(rig: Rig) -> None:
    rig.sim.send(b"\x01\x02\x03\x00" + b"\x55" * 300 + b"\x00" + b"\x05abc\x00")
    reply = rig.client.request(Hello(1, 0))
    assert isinstance(reply, Identify)
    cnt = rig.sim.firmware.counters
    assert cnt.oversize == 1
    assert cnt.bad_crc + cnt.bad_cobs + cnt.bad_length >= 2


def test_hello_forgets_replies_so_a_restarted_host_reusing_seqs_is_obeyed() -> None:
    from hil_sim.client import FrameClient
    from hil_sim.runner import Simulation
    from protocol import SCHEMA_HASH, Flag
    from protocol.messages import Hello, Identify, ParamSet

    sim = Simulation()
    client = FrameClient(sim)
    acked = Flag.ACK_REQUESTED
    client.send(Hello(1, SCHEMA_HASH, session_id=1), flags=acked, seq=0)
    client.send(ParamSet(1, 700), flags=acked, seq=1)
    client.send(ParamSet(1, 800), flags=acked, seq=2)
    client.run(5)
    # The host restarts (a new session id): HELLO again at seq 0, then the same body at seq 1.
    client.send(Hello(1, SCHEMA_HASH, session_id=2), flags=acked, seq=0)
    client.send(ParamSet(1, 700), flags=acked, seq=1)
    replies = [p.message for p in client.run(5)]
    assert any(isinstance(r, Identify) for r in replies)
    assert sim.firmware.params.values[1] == 700  # executed, not answered from the old cache


def test_commands_before_hello_are_refused_except_stops() -> None:
    """After a boot only HELLO, STOP and ESTOP are accepted: nothing stale runs twice."""
    from hil_sim.client import FrameClient
    from hil_sim.runner import Simulation
    from protocol.messages import Estop, Nak, ParamSet, Stop

    sim = Simulation()
    client = FrameClient(sim, handshake=False)
    refused = client.request(ParamSet(1, 700))
    assert isinstance(refused, Nak)
    assert refused.code == NakCode.HELLO_REQUIRED
    assert sim.firmware.params.values[1] != 700
    assert isinstance(client.request(Stop()), Ack)
    assert isinstance(client.request(Estop()), Ack)
