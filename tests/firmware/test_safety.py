"""Safety without the host: watchdog, e-stop, hard and soft limits, following error, homing."""

from __future__ import annotations

from firmware.controller import Firmware
from protocol import Fault, Inputs, NakCode, ParamId, State
from protocol.messages import Ack, ClearFault, Home, Jog, MoveTo, Nak, ParamSet, Stop
from tests.firmware.conftest import Rig, make_rig

SPEED_UM_S = 300_000
ACCEL_UM_S2 = 500_000


def state_of(fw: Firmware) -> State:
    """The controller state (a call, so type narrowing does not stick across commands)."""
    return fw.state


def test_watchdog_stops_motion_within_timeout_plus_stopping_distance(homed: Rig) -> None:
    c, fw, sim = homed.client, homed.sim.firmware, homed.sim
    assert isinstance(c.request(Jog(SPEED_UM_S, ACCEL_UM_S2)), Ack)
    c.run(2000)  # at cruise speed, heartbeats flowing
    assert fw.state is State.MOVING
    s_silent = sim.truth().s_mm
    watchdog_ms = fw.params.get(ParamId.WATCHDOG_MS)
    sim.step(watchdog_ms + 1)
    assert fw.faults & Fault.WATCHDOG
    sim.step(2000)
    assert state_of(fw) is State.FAULT
    assert not fw.profile.moving
    travelled_mm = sim.truth().s_mm - s_silent
    speed_mm_s = SPEED_UM_S / 1000
    decel_mm_s2 = fw.params.get(ParamId.STOP_DECEL_UM_S2) / 1000
    allowed_mm = speed_mm_s * (watchdog_ms + 2) / 1000 + speed_mm_s**2 / (2 * decel_mm_s2) + 2
    assert 0 < travelled_mm <= allowed_mm
    # The host is back: clear, and home again before any absolute motion (PROTOCOL §9).
    assert isinstance(c.request(ClearFault()), Ack)
    assert state_of(fw) is State.IDLE
    assert not fw.homed


def test_watchdog_faults_a_standing_controller_too(homed: Rig) -> None:
    # PROTOCOL §9: from IDLE, HOMING, READY or MOVING; a silent host is noticed before motion.
    fw = homed.sim.firmware
    homed.sim.step(fw.params.get(ParamId.WATCHDOG_MS) + 2)
    assert fw.faults == Fault.WATCHDOG
    assert fw.state is State.FAULT


def test_estop_input_latches_until_clear_fault(homed: Rig) -> None:
    c, fw, sim = homed.client, homed.sim.firmware, homed.sim
    c.request(Jog(SPEED_UM_S, ACCEL_UM_S2))
    c.run(500)
    sim.press_estop()
    c.run(2)
    assert fw.state is State.ESTOP
    assert not sim.plant.drive_on
    reply = c.request(ClearFault())
    assert isinstance(reply, Nak), "input still asserted"
    sim.press_estop(False)
    c.run(500)
    assert fw.state is State.ESTOP, "the latch outlives the input"
    assert isinstance(c.request(ClearFault()), Ack)
    assert state_of(fw) is State.IDLE, "the drive was off: home again"
    assert sim.plant.drive_on


def test_hard_limit_stops_at_once_and_allows_moving_off(rig: Rig) -> None:
    c, fw, sim = rig.client, rig.sim.firmware, rig.sim
    limit = sim.scenario.track.limit_min_s_mm
    assert isinstance(c.request(Jog(-SPEED_UM_S, ACCEL_UM_S2)), Ack)  # unhomed: no soft limit
    for _ in range(100):
        c.run(100)
        if fw.state is not State.MOVING:
            break
    assert fw.state is State.FAULT
    assert fw.faults & Fault.HARD_LIMIT
    c.run(500)
    # Steps stop at once; the trolley's inertia still carries it a little past the switch.
    assert limit - 40 < sim.truth().s_mm <= limit
    c.request(ClearFault())
    reply = c.request(Jog(-SPEED_UM_S, ACCEL_UM_S2))
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.BEYOND_LIMIT
    assert isinstance(c.request(Jog(SPEED_UM_S, ACCEL_UM_S2)), Ack)
    c.run(1000)
    assert sim.truth().s_mm > limit + 50
    assert fw.faults == Fault.NONE


def test_jog_stops_exactly_at_soft_limit(homed: Rig) -> None:
    c, fw = homed.client, homed.sim.firmware
    c.request(ParamSet(ParamId.SOFT_LIMIT_MAX_UM, 400_000))
    c.request(Jog(SPEED_UM_S, ACCEL_UM_S2))
    peak = 0
    for _ in range(40):
        c.run(100)
        peak = max(peak, fw.profile.pos_sub)
    assert fw.state is State.READY
    assert peak <= fw.profile.hi_sub
    assert abs(fw.position_um - 400_000) < 150
    reply = c.request(Jog(SPEED_UM_S, ACCEL_UM_S2))
    assert isinstance(reply, Nak)
    assert reply.code == NakCode.BEYOND_LIMIT


def test_missed_steps_trip_following_error_and_lose_home(homed: Rig) -> None:
    c, fw, sim = homed.client, homed.sim.firmware, homed.sim
    c.request(MoveTo(300_000, SPEED_UM_S, ACCEL_UM_S2))
    c.run(200)
    sim.inject_missed_steps(4 * 64)  # four electrical cycles lost: 320 counts > 200
    c.run(5)
    assert fw.faults & Fault.FOLLOWING_ERROR
    assert fw.state is State.FAULT
    assert not fw.profile.moving
    c.request(ClearFault())
    assert state_of(fw) is State.IDLE
    assert not fw.homed
    assert isinstance(c.request(MoveTo(100_000, SPEED_UM_S, ACCEL_UM_S2)), Nak)


def test_homing_fails_after_its_travel(rig: Rig) -> None:
    c, fw = rig.client, rig.sim.firmware
    c.request(ParamSet(ParamId.HOMING_TRAVEL_UM, 50_000))  # the switch is 150 mm away
    assert isinstance(c.request(Home(0)), Ack)
    c.run(3000)
    assert fw.faults & Fault.HOMING_FAILED
    assert fw.state is State.FAULT
    assert not fw.homed


def test_homing_lands_on_the_index_with_the_offset() -> None:
    rig = make_rig(seed=3, start_s_mm=600.0)
    c, fw, sim = rig.client, rig.sim.firmware, rig.sim
    c.request(ParamSet(ParamId.HOME_OFFSET_UM, 1_000))
    c.request(Home(0))
    c.run(20_000)
    assert fw.state is State.READY
    assert fw.homed
    assert fw.inputs & Inputs.HOMED
    assert abs(fw.position_um - 1_000) < 200  # rotor lag under friction + one count
    # At the index the shaft angle is a whole number of turns.
    turns = sim.truth().sprocket_rad / (2 * 3.141592653589793)
    assert abs(turns - round(turns)) < 2e-3


def test_stop_aborts_homing_unhomed(rig: Rig) -> None:
    c, fw = rig.client, rig.sim.firmware
    c.request(Home(0))
    c.run(100)
    assert isinstance(c.request(Stop()), Ack)
    c.run(500)
    assert fw.state is State.IDLE
    assert not fw.homed


def test_soft_window_cannot_change_while_moving(homed: Rig) -> None:
    c, fw = homed.client, homed.sim.firmware
    c.request(Jog(SPEED_UM_S, ACCEL_UM_S2))
    c.run(100)
    reply = c.request(ParamSet(ParamId.SOFT_LIMIT_MAX_UM, 10_000))
    assert isinstance(reply, Nak)
    assert (reply.code, reply.state) == (NakCode.BAD_STATE, State.MOVING)
    assert fw.params.get(ParamId.SOFT_LIMIT_MAX_UM) == 16_283_185
