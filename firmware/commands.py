"""Command handling: decode, range-check, duplicate suppression, state rules and replies.

Every command declared host → controller is answered with its schema `reply`. A command that
is refused changes nothing and gets a NAK naming the reason and the state that refused it.
Replies to frames sent with ACK_REQUESTED are cached by seq and content, so a retransmitted
command is answered again from the cache and never executed twice.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from firmware.config import FW_VERSION, MAX_FRAME_BYTES, MCU_CLOCK_HZ, RX_WINDOW
from protocol import (
    PARAMS_BY_ID,
    PROTOCOL_VERSION,
    SCHEMA,
    SCHEMA_HASH,
    Direction,
    Flag,
    Inputs,
    NakCode,
    ParamId,
    PayloadError,
    State,
    decode_payload,
)
from protocol import messages as m
from protocol.compat import LEGACY_VERSION, decode_handshake
from protocol.schema import HEADER_SIZE, TEXT

if TYPE_CHECKING:
    from firmware.controller import Firmware

Reply = object
Handler = Callable[["Firmware", int, object], Reply]

_BODY_START = HEADER_SIZE - 1  # message id + payload: what makes a retransmission identical
_HALTED = (State.FAULT, State.ESTOP)
_NO_PARAM_WRITES = (State.BOOT, State.HOMING, State.MOVING)
_BUSY_MOVING = (State.FAULT, State.ESTOP, State.HOMING)

# Per command id: (field name, lo, hi) of every field, from the schema's declared bounds.
_CHECKS: dict[int, tuple[tuple[str, int, int], ...]] = {
    spec.id: tuple((f.name, *f.info.bounds()) for f in spec.fields if f.wire is not TEXT)
    for spec in SCHEMA.specs()
    if spec.direction is not Direction.TO_HOST
}


_HELLO_ID = SCHEMA.by_cls[m.Hello].id
# Stopping never waits: STOP and ESTOP run on arrival, ahead of any gap (PROTOCOL §6, R-ORDER-3),
# and before a HELLO (a stale stop replayed after a reboot does no harm).
_STOP_IDS = frozenset(SCHEMA.by_cls[c].id for c in (m.Stop, m.Estop))
# Ids whose schema says acked: only these take a place in the command sequence.
_ACKED_IDS = frozenset(spec.id for spec in SCHEMA.specs() if spec.acked)
_SEQ_MOD = 0x1_0000
_SEQ_HALF = _SEQ_MOD // 2


def handle(
    fw: Firmware, seq: int, flags: int, msg_id: int, raw: bytes, version: int = PROTOCOL_VERSION
) -> None:
    """Act on one checked frame: unacked at once, acked commands in sequence order."""
    if version != PROTOCOL_VERSION:
        _foreign_hello(fw, seq, version, raw)
        return
    # HELLO is always answered, flag or not: it is how any client, of any version, asks.
    acked = bool(flags & Flag.ACK_REQUESTED) or msg_id == _HELLO_ID
    if not acked or (msg_id not in _ACKED_IDS and msg_id in _CHECKS):
        # Unacked traffic (HEARTBEAT, CLOCK_SYNC), with or without a stray ACK_REQUESTED, takes
        # no place in the sequence. An acked-only command without the flag runs only if it stops.
        if msg_id in _ACKED_IDS and msg_id not in _STOP_IDS:
            fw.counters.unacked_commands += 1
            return
        reply = _execute(fw, seq, msg_id, raw, acked=False)
        if reply is not None and msg_id not in _ACKED_IDS:
            fw.tx.send(reply, reply=True)  # CLOCK_SYNC_REPLY: the only unacked answer
        return
    body = raw[_BODY_START:]
    if msg_id == _HELLO_ID:
        _handle_hello(fw, seq, body, raw)
        return
    if not fw.hello_seen and msg_id not in _STOP_IDS:
        # After a reboot the reply memory is empty: a retransmission from before the reboot would
        # run a second time. Refuse until the host has noticed the reboot and said HELLO.
        fw.tx.send(_nak(fw, seq, NakCode.HELLO_REQUIRED), reply=True)
        return
    remembered = fw.replies.lookup(seq)
    if remembered is not None:
        _answer_repeat(fw, seq, body, remembered)
        return
    ahead = (seq - fw.next_cmd_seq) % _SEQ_MOD
    if msg_id in _STOP_IDS:
        _run_stop(fw, seq, msg_id, raw, ahead)
    elif ahead == 0:
        _run_in_order(fw, seq, msg_id, raw)
    elif ahead >= _SEQ_HALF:
        fw.counters.stale += 1  # behind the sequence: its turn has passed
        fw.tx.send(_nak(fw, seq, NakCode.STALE_SEQ), reply=True)
    elif ahead <= RX_WINDOW:
        fw.counters.held += seq not in fw.held
        fw.held.put(seq, Flag.ACK_REQUESTED, msg_id, raw)
    else:
        fw.tx.send(_nak(fw, seq, NakCode.BUSY), reply=True)  # not held, not remembered


def _foreign_hello(fw: Firmware, seq: int, version: int, raw: bytes) -> None:
    """Another version's HELLO: say who we are, in a framing it reads, and change nothing."""
    if decode_handshake(_HELLO_ID, raw[HEADER_SIZE:]) is None:
        return
    identify = _hello(fw, seq, None)
    fw.tx.send(identify, reply=True, legacy=version == LEGACY_VERSION)


def _handle_hello(fw: Firmware, seq: int, body: bytes, raw: bytes) -> None:
    """Start a command sequence at the HELLO's seq; a repeat of the same HELLO resets nothing."""
    remembered = fw.replies.lookup(seq)
    if fw.hello_seen and remembered is not None and remembered[0] == body:
        fw.counters.duplicates += 1
        fw.tx.send(remembered[1], reply=True)
        return
    # A (re)starting host may reuse old seqs: forget every reply and held frame (PROTOCOL §6).
    fw.replies.clear()
    fw.held.clear()
    fw.hello_seen = True
    fw.next_cmd_seq = (seq + 1) % _SEQ_MOD
    _finish(fw, seq, body, _execute(fw, seq, _HELLO_ID, raw, acked=True))


def _answer_repeat(fw: Firmware, seq: int, body: bytes, remembered: tuple[bytes, object]) -> None:
    """A remembered seq: the same command gets its reply again; other content is refused."""
    if remembered[0] == body:
        fw.counters.duplicates += 1
        fw.tx.send(remembered[1], reply=True)
    else:
        fw.counters.stale += 1
        fw.tx.send(_nak(fw, seq, NakCode.STALE_SEQ), reply=True)


def _run_in_order(fw: Firmware, seq: int, msg_id: int, raw: bytes) -> None:
    """Execute the next command of the sequence, then every held one it unblocks."""
    while True:
        fw.next_cmd_seq = (seq + 1) % _SEQ_MOD
        _finish(fw, seq, raw[_BODY_START:], _execute(fw, seq, msg_id, raw, acked=True))
        held = None if fw.reboot_pending else fw.held.pop(fw.next_cmd_seq)
        if held is None:
            return
        seq = fw.next_cmd_seq
        _, msg_id, raw = held


def _run_stop(fw: Firmware, seq: int, msg_id: int, raw: bytes, ahead: int) -> None:
    """STOP/ESTOP run on arrival; every older command that has not run yet never will."""
    if ahead >= _SEQ_HALF:
        # Behind the sequence and forgotten: stopping is never unsafe, so it still runs, but
        # it does not move the sequence back.
        reply = _execute(fw, seq, msg_id, raw, acked=True)
        _finish(fw, seq, raw[_BODY_START:], reply, in_sequence=False)
        return
    for old in fw.held.seqs():
        if (old - seq) % _SEQ_MOD >= _SEQ_HALF:  # older than the stop: cancelled
            _, _, old_raw = fw.held.pop(old) or (0, 0, b"")
            _finish(fw, old, old_raw[_BODY_START:], _nak(fw, old, NakCode.STALE_SEQ))
    _run_in_order(fw, seq, msg_id, raw)


def _finish(
    fw: Firmware, seq: int, body: bytes, reply: Reply | None, in_sequence: bool = True
) -> None:
    """Remember and queue the reply of a handled command; STATUS reports the last in sequence."""
    if reply is None:
        return
    if in_sequence:
        fw.last_cmd_seq = seq
    fw.replies.store(seq, body, reply)
    fw.tx.send(reply, reply=True)


def _execute(fw: Firmware, seq: int, msg_id: int, raw: bytes, acked: bool) -> Reply | None:
    """Decode, validate and dispatch; None when nothing is to be answered."""
    checks = _CHECKS.get(msg_id)
    if checks is None:
        return _nak(fw, seq, NakCode.UNKNOWN_MESSAGE) if acked else None
    try:
        msg = decode_payload(msg_id, raw, HEADER_SIZE)
    except PayloadError:
        return _nak(fw, seq, NakCode.BAD_PAYLOAD) if acked else None
    for name, lo, hi in checks:
        if not lo <= getattr(msg, name) <= hi:
            return _nak(fw, seq, NakCode.OUT_OF_RANGE)
    return _HANDLERS[type(msg)](fw, seq, msg)


def _ack(fw: Firmware, seq: int) -> m.Ack:
    """ACK carrying the state after the command."""
    return m.Ack(seq, fw.state)


def _nak(fw: Firmware, seq: int, code: NakCode) -> m.Nak:
    """NAK carrying the reason and the state that refused."""
    return m.Nak(seq, code, fw.state)


# ---- session ----------------------------------------------------------------------------


def _hello(fw: Firmware, seq: int, msg: object) -> Reply:
    """IDENTIFY, whatever the host's version: the host decides whether it can talk to us."""
    if isinstance(msg, m.Hello):
        fw.start_session(msg.capabilities)  # a foreign HELLO (msg None) opens no session
    return m.Identify(
        seq,
        PROTOCOL_VERSION,
        SCHEMA_HASH,
        FW_VERSION,
        fw.boot_id,
        fw.mech.encoder_counts_per_rev,
        fw.mech.steps_per_rev,
        fw.mech.sprocket_teeth,
        fw.mech.chain_pitch_um,
        MCU_CLOCK_HZ,
        MAX_FRAME_BYTES,
        RX_WINDOW,
        fw.state,
        fw.capabilities,
    )


def _heartbeat(fw: Firmware, seq: int, msg: object) -> Reply | None:
    """Nothing to answer: the frame already fed the watchdog."""
    return None


def _clock_sync(fw: Firmware, seq: int, msg: object) -> Reply:
    """The controller clock when the probe arrived and now, as the reply is queued.

    The host subtracts the difference (the probe's wait for this tick) from the round trip.
    """
    assert isinstance(msg, m.ClockSync)
    fw.clock_probe_arrived(fw.frame_rx_us)
    return m.ClockSyncReply(
        seq, msg.token, fw.hal.micros() & 0xFFFF_FFFF, fw.frame_rx_us & 0xFFFF_FFFF
    )


def _reset(fw: Firmware, seq: int, msg: object) -> Reply:
    """Acknowledge now, reboot on the next tick."""
    fw.request_reboot()
    return _ack(fw, seq)


# ---- motion -----------------------------------------------------------------------------


def _home(fw: Firmware, seq: int, msg: object) -> Reply:
    """Start homing from IDLE or READY."""
    assert isinstance(msg, m.Home)
    if fw.state not in (State.IDLE, State.READY):
        return _nak(fw, seq, NakCode.BAD_STATE)
    if msg.speed_um_s > fw.params.get(ParamId.MAX_SPEED_UM_S):
        return _nak(fw, seq, NakCode.OUT_OF_RANGE)
    if fw.switches & Inputs.LIMIT_MIN:
        return _nak(fw, seq, NakCode.BEYOND_LIMIT)
    fw.start_homing(msg.speed_um_s)
    return _ack(fw, seq)


def _move_to(fw: Firmware, seq: int, msg: object) -> Reply:
    """Absolute move within the soft limits, once homed."""
    assert isinstance(msg, m.MoveTo)
    if fw.state in _BUSY_MOVING:
        return _nak(fw, seq, NakCode.BAD_STATE)
    if not fw.homed:
        return _nak(fw, seq, NakCode.NOT_HOMED)
    lo = fw.params.get(ParamId.SOFT_LIMIT_MIN_UM)
    hi = fw.params.get(ParamId.SOFT_LIMIT_MAX_UM)
    if not lo <= msg.position_um <= hi:
        return _nak(fw, seq, NakCode.BEYOND_LIMIT)
    target = fw.mech.um_to_steps(msg.position_um)
    if _toward_closed_limit(fw, target - fw.profile.steps):
        return _nak(fw, seq, NakCode.BEYOND_LIMIT)
    vmax = _capped_speed(fw, msg.speed_um_s)
    fw.profile.move_to(target, vmax, _capped_accel(fw, msg.accel_um_s2), fw.stop_decel)
    fw.state = State.MOVING if fw.profile.moving else State.READY
    return _ack(fw, seq)


def _jog(fw: Firmware, seq: int, msg: object) -> Reply:
    """Run at a velocity until STOP, another motion or a soft limit."""
    assert isinstance(msg, m.Jog)
    if fw.state in _BUSY_MOVING:
        return _nak(fw, seq, NakCode.BAD_STATE)
    v = msg.velocity_um_s
    if v and (_toward_closed_limit(fw, v) or _at_soft_limit(fw, v)):
        return _nak(fw, seq, NakCode.BEYOND_LIMIT)
    vel = _capped_speed(fw, abs(v)) * (1 if v > 0 else -1) if v else 0
    fw.profile.jog(vel, _capped_accel(fw, msg.accel_um_s2), fw.stop_decel)
    if fw.profile.moving:
        fw.state = State.MOVING
    return _ack(fw, seq)


def _stop(fw: Firmware, seq: int, msg: object) -> Reply:
    """Controlled stop; aborting homing leaves the controller unhomed."""
    fw.profile.stop(fw.stop_decel)
    if fw.state is State.HOMING:
        fw.set_homed(False)
        fw.state = State.MOVING if fw.profile.moving else State.IDLE
    return _ack(fw, seq)


def _estop(fw: Firmware, seq: int, msg: object) -> Reply:
    """Emergency stop, latched."""
    fw.estop()
    return _ack(fw, seq)


def _clear_fault(fw: Firmware, seq: int, msg: object) -> Reply:
    """Release latched faults; refused while the e-stop input is still asserted."""
    if fw.state not in _HALTED:
        return _ack(fw, seq)
    if fw.switches & Inputs.ESTOP_IN:
        return _nak(fw, seq, NakCode.BAD_STATE)
    fw.clear_faults()
    return _ack(fw, seq)


def _head_set(fw: Firmware, seq: int, msg: object) -> Reply:
    """Point the head, unless halted."""
    assert isinstance(msg, m.HeadSet)
    if fw.state in _HALTED:
        return _nak(fw, seq, NakCode.BAD_STATE)
    fw.hal.head_set(msg.pan_urad, msg.tilt_urad)
    return _ack(fw, seq)


# ---- parameters and streams -------------------------------------------------------------


def _param_get(fw: Firmware, seq: int, msg: object) -> Reply:
    """A parameter's value in force."""
    assert isinstance(msg, m.ParamGet)
    if msg.param_id not in PARAMS_BY_ID:
        return _nak(fw, seq, NakCode.UNKNOWN_PARAM)
    return m.ParamValue(seq, msg.param_id, fw.params.values[msg.param_id])


def _param_set(fw: Firmware, seq: int, msg: object) -> Reply:
    """Set a parameter in RAM within its range; the soft window only at standstill, ordered."""
    assert isinstance(msg, m.ParamSet)
    pid = msg.param_id
    if fw.state in _NO_PARAM_WRITES or fw.profile.moving:
        # Limits and speeds change only at standstill (PROTOCOL §10): a ceiling lowered under a
        # running profile could only be honoured by a halt.
        return _nak(fw, seq, NakCode.BAD_STATE)
    if pid not in PARAMS_BY_ID:
        return _nak(fw, seq, NakCode.UNKNOWN_PARAM)
    old = fw.params.values[pid]
    if not fw.params.set(pid, msg.value) or not _limits_ordered(fw):
        fw.params.values[pid] = old
        return _nak(fw, seq, NakCode.OUT_OF_RANGE)
    fw.update_bounds()
    return m.ParamValue(seq, pid, fw.params.values[pid])


def _param_persist(fw: Firmware, seq: int, msg: object) -> Reply:
    """Write the parameter record to flash, at standstill only (a flash write stalls the CPU)."""
    if fw.state in _NO_PARAM_WRITES or fw.profile.moving:
        return _nak(fw, seq, NakCode.BAD_STATE)
    if not fw.hal.flash_write(fw.params.encode()):
        return _nak(fw, seq, NakCode.FLASH_ERROR)
    return _ack(fw, seq)


def _stream_set(fw: Firmware, seq: int, msg: object) -> Reply:
    """Switch a telemetry stream."""
    assert isinstance(msg, m.StreamSet)
    fw.set_stream(msg.stream, msg.rate_hz)
    return _ack(fw, seq)


# ---- helpers ----------------------------------------------------------------------------


def _capped_speed(fw: Firmware, um_s: int) -> int:
    """Requested speed, never above MAX_SPEED_UM_S, in profile units."""
    return fw.mech.speed_to_msteps(min(um_s, fw.params.get(ParamId.MAX_SPEED_UM_S)))


def _capped_accel(fw: Firmware, um_s2: int) -> int:
    """Requested acceleration, never above MAX_ACCEL_UM_S2, in profile units."""
    return fw.mech.accel_to_msteps_per_tick(min(um_s2, fw.params.get(ParamId.MAX_ACCEL_UM_S2)))


def _toward_closed_limit(fw: Firmware, direction: int) -> bool:
    """Whether a motion in this direction would drive into a closed limit switch."""
    sw = fw.switches
    if direction > 0:
        return bool(sw & Inputs.LIMIT_MAX)
    return direction < 0 and bool(sw & Inputs.LIMIT_MIN)


def _at_soft_limit(fw: Firmware, direction: int) -> bool:
    """Whether the commanded position already sits on the soft limit in this direction."""
    if not fw.homed:
        return False
    p = fw.profile
    return p.pos_sub >= p.hi_sub if direction > 0 else p.pos_sub <= p.lo_sub


def _limits_ordered(fw: Firmware) -> bool:
    """Soft-limit window not inverted."""
    v = fw.params.values
    return v[ParamId.SOFT_LIMIT_MIN_UM] <= v[ParamId.SOFT_LIMIT_MAX_UM]


_HANDLERS: dict[type, Callable[[Firmware, int, object], Reply | None]] = {
    m.Hello: _hello,
    m.Heartbeat: _heartbeat,
    m.ClockSync: _clock_sync,
    m.Reset: _reset,
    m.Home: _home,
    m.MoveTo: _move_to,
    m.Jog: _jog,
    m.Stop: _stop,
    m.Estop: _estop,
    m.ClearFault: _clear_fault,
    m.HeadSet: _head_set,
    m.ParamGet: _param_get,
    m.ParamSet: _param_set,
    m.ParamPersist: _param_persist,
    m.StreamSet: _stream_set,
}
