"""Commands take effect in seq order (PROTOCOL.md §6): held across a gap, stops never wait."""

from __future__ import annotations

from firmware import config
from protocol import Flag, NakCode, ParamId, State
from protocol.messages import (
    Ack,
    Heartbeat,
    Home,
    Jog,
    MoveTo,
    Nak,
    ParamSet,
    ParamValue,
    Status,
    Stop,
)
from tests.firmware.conftest import Rig

ACKED = Flag.ACK_REQUESTED
SPEED_UM_S = 200_000
ACCEL_UM_S2 = 500_000


def replies_to(rig: Rig, seq: int) -> list[object]:
    """Every reply received so far that names seq."""
    return [p.message for p in rig.client.received if getattr(p.message, "req_seq", -1) == seq]


def test_a_command_ahead_of_a_gap_waits_for_it_then_both_run_in_order(rig: Rig) -> None:
    c, fw = rig.client, rig.sim.firmware
    first, second = c.seq, (c.seq + 1) & 0xFFFF
    c.seq = (c.seq + 2) & 0xFFFF
    c.send(ParamSet(ParamId.MAX_SPEED_UM_S, 70_000), flags=ACKED, seq=second)
    c.run(20)
    assert replies_to(rig, second) == [], "held until the gap fills"
    assert fw.params.get(ParamId.MAX_SPEED_UM_S) != 70_000
    assert fw.counters.held == 1
    # The lost first command arrives (a retransmission): it runs, then the held one.
    c.send(ParamSet(ParamId.MAX_SPEED_UM_S, 60_000), flags=ACKED, seq=first)
    c.run(5)
    assert replies_to(rig, first) == [ParamValue(first, ParamId.MAX_SPEED_UM_S, 60_000)]
    assert replies_to(rig, second) == [ParamValue(second, ParamId.MAX_SPEED_UM_S, 70_000)]
    assert fw.params.get(ParamId.MAX_SPEED_UM_S) == 70_000, "the later command took effect last"


def test_stop_ahead_of_a_gap_runs_at_once_and_cancels_older_commands(homed: Rig) -> None:
    c, fw = homed.client, homed.sim.firmware
    assert isinstance(c.request(Jog(SPEED_UM_S, ACCEL_UM_S2)), Ack)
    c.run(300)
    lost, held, stop = c.seq, (c.seq + 1) & 0xFFFF, (c.seq + 2) & 0xFFFF
    c.seq = (c.seq + 3) & 0xFFFF
    c.send(MoveTo(5_000_000, SPEED_UM_S, ACCEL_UM_S2), flags=ACKED, seq=held)
    c.send(Stop(), flags=ACKED, seq=stop)
    c.run(2)
    assert isinstance(replies_to(homed, stop)[0], Ack), "STOP did not wait for the gap"
    cancelled = replies_to(homed, held)[0]
    assert isinstance(cancelled, Nak)
    assert cancelled.code == NakCode.STALE_SEQ
    # The lost command turns up after the stop: it never runs.
    c.send(MoveTo(6_000_000, SPEED_UM_S, ACCEL_UM_S2), flags=ACKED, seq=lost)
    c.run(1500)
    late = replies_to(homed, lost)[0]
    assert isinstance(late, Nak)
    assert late.code == NakCode.STALE_SEQ
    assert fw.state is State.READY
    assert not fw.profile.moving


def test_a_command_too_far_ahead_is_busy_and_not_remembered(rig: Rig) -> None:
    c, fw = rig.client, rig.sim.firmware
    far = (c.seq + config.RX_WINDOW + 1) & 0xFFFF
    c.send(ParamSet(ParamId.WATCHDOG_MS, 900), flags=ACKED, seq=far)
    c.run(2)
    busy = replies_to(rig, far)[0]
    assert isinstance(busy, Nak)
    assert busy.code == NakCode.BUSY
    assert len(fw.replies) == 1  # only the HELLO's IDENTIFY


def test_a_seq_behind_the_sequence_is_stale(rig: Rig) -> None:
    c = rig.client
    assert isinstance(c.request(ParamSet(ParamId.WATCHDOG_MS, 900)), ParamValue)
    old = (c.seq - 40) & 0xFFFF
    c.send(ParamSet(ParamId.WATCHDOG_MS, 950), flags=ACKED, seq=old)
    c.run(2)
    stale = replies_to(rig, old)[0]
    assert isinstance(stale, Nak)
    assert stale.code == NakCode.STALE_SEQ
    assert rig.sim.firmware.params.get(ParamId.WATCHDOG_MS) == 900


def test_a_command_without_ack_requested_is_ignored_unless_it_stops(homed: Rig) -> None:
    c, fw = homed.client, homed.sim.firmware
    c.send(MoveTo(3_000_000, SPEED_UM_S, ACCEL_UM_S2), flags=Flag.NONE)
    c.run(50)
    assert fw.state is State.READY
    assert fw.counters.unacked_commands == 1
    assert isinstance(c.request(Jog(SPEED_UM_S, ACCEL_UM_S2)), Ack)
    c.run(200)
    c.send(Stop(), flags=Flag.NONE)
    c.run(1500)
    assert fw.state is State.READY


def test_heartbeat_with_ack_requested_is_not_answered_and_spends_no_seq(rig: Rig) -> None:
    c = rig.client
    seq = c.seq
    c.send(Heartbeat(1), flags=ACKED, seq=seq)
    c.run(5, heartbeat_ms=1000)
    assert replies_to(rig, seq) == []
    assert isinstance(c.request(ParamSet(ParamId.WATCHDOG_MS, 700)), ParamValue)


def test_status_is_sent_on_every_state_change_with_streams_off(homed: Rig) -> None:
    c = homed.client
    seq = c.send(MoveTo(400_000, SPEED_UM_S, ACCEL_UM_S2))
    c.run(3000)
    states = [(s.state, s.cmd_seq) for s in c.of_type(Status)]
    assert (State.MOVING, seq) in states
    assert states[-1] == (State.READY, seq), "motion complete: READY after this command"


def test_param_writes_while_moving_are_bad_state(homed: Rig) -> None:
    c = homed.client
    assert isinstance(c.request(Jog(SPEED_UM_S, ACCEL_UM_S2)), Ack)
    c.run(100)
    for reply in (c.request(ParamSet(ParamId.MAX_SPEED_UM_S, 90_000)),):
        assert isinstance(reply, Nak)
        assert (reply.code, reply.state) == (NakCode.BAD_STATE, State.MOVING)
    assert homed.sim.firmware.params.get(ParamId.MAX_SPEED_UM_S) != 90_000


def test_home_again_from_the_homed_position_backs_off_past_the_switch(homed: Rig) -> None:
    # The index lies past the switch, so a homed trolley sits behind it: seeking straight in
    # the negative direction would run to LIMIT_MIN (issue 13). It backs off first (R-HOME-2).
    c, fw = homed.client, homed.sim.firmware
    first_switch = fw.switch_counts
    assert first_switch is not None
    assert fw.enc_pos <= first_switch, "the rig's index is behind its switch"
    assert isinstance(c.request(Home(0)), Ack)
    velocities = []
    for _ in range(400):
        c.run(100)
        velocities.append(fw.profile.vel)
        if fw.state is not State.HOMING:
            break
    assert fw.state is State.READY, fw.faults
    assert next(v for v in velocities if v) > 0, "the first motion is the back-off, positive"
    assert abs(homed.sim.firmware.position_um) < 2_000


def test_stop_during_homing_decelerates_as_moving_then_idle_unhomed(rig: Rig) -> None:
    c, fw = rig.client, rig.sim.firmware
    assert isinstance(c.request(Home(0)), Ack)
    c.run(300)
    reply = c.request(Stop())
    assert isinstance(reply, Ack)
    assert reply.state in (State.MOVING, State.IDLE)
    c.run(1000)
    assert fw.state is State.IDLE
    assert not fw.homed
