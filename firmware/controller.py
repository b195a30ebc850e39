"""The controller: boot, the 1 kHz tick, the state machine, safety, homing and telemetry.

`Firmware.tick()` is the whole main loop of the C build, called from the tick timer: read the
sensors, handle received frames, run the safety checks, advance homing and the step profile,
emit telemetry, flush the TX queue. Positions are ints (encoder counts, microsteps, µm); the
only clock is the HAL's wrapping microsecond timer.
"""

from __future__ import annotations

import enum

from firmware import commands
from firmware.batching import Batcher, Sample
from firmware.config import (
    CAPABILITIES,
    MECHANICS,
    SUB_PER_STEP,
    TICK_HZ,
    VELOCITY_FILTER_SHIFT,
    Mechanics,
)
from firmware.hal import Hal
from firmware.link import HoldBuffer, LinkCounters, ReplyCache, RxFramer, TxQueue
from firmware.motion import Profile
from firmware.quiet import QuietHold
from firmware.storage import LoadResult, ParamStore
from protocol import Fault, Inputs, ParamId, State, Stream
from protocol.enums import Capability
from protocol.messages import (
    EncoderSample,
    HeadSample,
    Heartbeat,
    RangeSample,
    RefMark,
    Status,
)

_SWITCH_INPUTS = int(Inputs.HOME | Inputs.LIMIT_MIN | Inputs.LIMIT_MAX | Inputs.ESTOP_IN)
# Plain ints for the tick's bit tests: IntFlag operators build enum objects on every call.
_IN_ESTOP = int(Inputs.ESTOP_IN)
_IN_LIMIT_MIN = int(Inputs.LIMIT_MIN)
_IN_LIMIT_MAX = int(Inputs.LIMIT_MAX)
_IN_HOME = int(Inputs.HOME)
_IN_HOMED = int(Inputs.HOMED)
_IN_INDEX = int(Inputs.INDEX)
# PROTOCOL.md: the controller sends HEARTBEAT after 250 ms without sending anything.
HEARTBEAT_IDLE_TICKS = 250
_F_FOLLOWING = int(Fault.FOLLOWING_ERROR)
_N_STREAMS = len(Stream)
_MOTION_STATES = (State.MOVING, State.HOMING)
_WATCHDOG_STATES = (State.IDLE, State.HOMING, State.READY, State.MOVING)
_BATCHED = int(Capability.BATCHED_TELEMETRY)
_QUIET = int(Capability.QUIET_CLOCK_PROBES)
_BATCH_AGE_PARAMS = {
    int(Stream.ENCODER): ParamId.ENCODER_BATCH_AGE_MS,
    int(Stream.RANGE): ParamId.RANGE_BATCH_AGE_MS,
    int(Stream.HEAD): ParamId.HEAD_BATCH_AGE_MS,
}
_BATCHED_STREAMS = tuple(_BATCH_AGE_PARAMS)


class HomingPhase(enum.Enum):
    """Where homing is."""

    BACKOFF = 3  # started on the switch: moving off it (positive) before the seek
    SEEK = 0  # moving toward the home switch
    INDEX = 1  # on the switch, waiting for the encoder index
    RETURN = 2  # index latched, moving back onto it


def _i32(x: int) -> int:
    """Wrap to a signed 32-bit value, as the C int32_t fields do."""
    return ((x + 0x8000_0000) & 0xFFFF_FFFF) - 0x8000_0000


class Firmware:
    """The controller mirror; construct it on a HAL (power-on), then call tick() at 1 kHz."""

    # Controller state, initialised by _boot (the C keeps these in one static struct).
    boot_id: int
    state: State
    faults: int  # Fault bits
    homed: bool
    ticks: int
    now_us: int
    enc_raw: int
    enc_pos: int  # encoder counts from home (from reset until homed)
    velocity: int  # filtered encoder velocity, counts/s
    switches: int
    index_latch: int | None  # index position this tick, extended counter coordinates
    index_seen: bool
    hello_seen: bool  # a HELLO since boot: until then acked commands other than stops are refused
    next_cmd_seq: int  # the seq of the acked command whose turn it is (PROTOCOL §6)
    last_cmd_seq: int  # the last acked command handled in sequence, reported in STATUS
    frame_rx_us: int  # µs timer when the delimiter of the frame being handled arrived
    watchdog_armed: bool
    last_rx_tick: int
    _last_tx_tick: int  # when the controller last sent anything (heartbeat when idle)
    homing_phase: HomingPhase
    homing_speed: int
    homing_origin: int
    switch_counts: int | None  # encoder position where the home switch closed when last homed
    stream_rates: list[int]
    stream_acc: list[int]
    active_streams: list[int]

    def __init__(
        self, hal: Hal, capabilities: int = CAPABILITIES, mechanics: Mechanics = MECHANICS
    ) -> None:
        self.hal = hal
        self.mech = mechanics  # the drive this build is for (the C's build-time constants)
        self.capabilities = capabilities  # offered in IDENTIFY (0: a controller without batching)
        self.batching = False  # both sides offered BATCHED_TELEMETRY in this session
        self.quiet_probes = False  # both sides offered QUIET_CLOCK_PROBES in this session
        self.quiet = QuietHold()  # telemetry held for a probe pair
        self.batchers = {s: Batcher() for s in _BATCHED_STREAMS}
        self.counters = LinkCounters()
        self.params = ParamStore()
        self.rx = RxFramer(self.counters)
        self.tx = TxQueue(self.counters)
        self.replies = ReplyCache()
        self.held = HoldBuffer()
        self.profile = Profile()
        self.boots = 0
        self._reboot_pending = False
        self._boot()

    # ---- public --------------------------------------------------------------------------

    def tick(self) -> None:
        """One pass of the main loop (1 ms)."""
        if self._reboot_pending:
            self.hal.system_reset()
            self._boot()
        self.now_us = self.tx.now_us = self.hal.micros()
        self.ticks += 1
        if held_us := self.quiet.tick(self.now_us):
            self.tx.delay_telemetry(held_us)  # what it held keeps its spacing (firmware.link)
        self._read_sensors()
        data, at_us = self.hal.link_read()
        if data:
            self._receive(data, at_us)
        self._safety()
        if self.state is State.HOMING:
            self._homing()
        steps = self.profile.tick()
        self.hal.step_out(steps)
        if self.state in _MOTION_STATES and not self.profile.moving:
            self.state = State.READY if self.homed else State.IDLE
        if self.active_streams:
            self._telemetry()
        if self.batching:
            self._send_due_batches()
        if (self.state, self.faults) != self._reported:
            # Every state or fault change is reported, streams on or off (PROTOCOL §10).
            self.tx.send(self._status(), reply=True)
        if self.ticks - self._last_tx_tick >= HEARTBEAT_IDLE_TICKS:
            self.tx.send(Heartbeat(self.ticks & 0xFFFF_FFFF))
        out = self.tx.drain(self.hal.link_tx_room(), telemetry=not self.quiet.active)
        if out:
            self.hal.link_write(out)
            self._last_tx_tick = self.ticks

    def request_reboot(self) -> None:
        """Reboot at the start of the next tick (after the current replies went out)."""
        self._reboot_pending = True

    @property
    def reboot_pending(self) -> bool:
        """A RESET was acknowledged: nothing more runs before the reboot."""
        return self._reboot_pending

    @property
    def position_um(self) -> int:
        """Encoder position from home, µm."""
        return self.mech.counts_to_um(self.enc_pos)

    @property
    def inputs(self) -> int:
        """Input and position flags as reported in telemetry."""
        return self.switches | (_IN_HOMED if self.homed else 0)

    # ---- state changes used by the command handlers -----------------------------------------

    def latch_fault(self, fault: Fault, halt: bool) -> None:
        """Latch a fault; stop at once (halt) or at STOP_DECEL, and enter FAULT."""
        self.faults |= int(fault)
        if halt:
            self.profile.halt()
        else:
            self.profile.stop(self.stop_decel)
        if self.state is not State.ESTOP:
            self.state = State.FAULT

    def estop(self) -> None:
        """Drive off at once and latch ESTOP."""
        self.profile.halt()
        self.hal.drive_enable(False)
        self.faults |= int(Fault.ESTOP)
        self.state = State.ESTOP

    def clear_faults(self) -> None:
        """Release the latches: IDLE and unhomed, whatever the fault (PROTOCOL §10: home again).

        The commanded position is resynchronised to the encoder once the drive stands still.
        """
        self.set_homed(False)
        self.faults = 0
        self.hal.drive_enable(True)
        if not self.profile.moving:
            self.profile.shift(self.mech.counts_to_steps(self.enc_pos) - self.profile.steps)
            self.state = State.IDLE
        else:
            self.state = State.MOVING

    def set_homed(self, homed: bool) -> None:
        """Set the homed flag and the soft-limit window that goes with it."""
        self.homed = homed
        self.update_bounds()

    def update_bounds(self) -> None:
        """Apply the soft limits to the profile (only once homed)."""
        if not self.homed:
            self.profile.set_bounds(None, None)
            return
        lo = self.mech.um_to_steps(self.params.get(ParamId.SOFT_LIMIT_MIN_UM))
        hi = self.mech.um_to_steps(self.params.get(ParamId.SOFT_LIMIT_MAX_UM))
        lo += self.mech.steps_to_um(lo) < self.params.get(ParamId.SOFT_LIMIT_MIN_UM)
        hi -= self.mech.steps_to_um(hi) > self.params.get(ParamId.SOFT_LIMIT_MAX_UM)
        self.profile.set_bounds(lo, hi)

    def start_homing(self, speed_um_s: int) -> None:
        """Begin homing: seek the home switch in the negative direction."""
        # On the switch, or homed and behind it (the index lies past the switch, so a homed
        # trolley usually is): back off past it first, so the switch is always met from the
        # positive side and the index latched is the same one (PROTOCOL §10, R-HOME-2).
        # The encoder keeps counting through faults and CLEAR_FAULT, so where the switch was
        # stays known until a reboot even when the reference is no longer trusted.
        on_switch = bool(self.switches & _IN_HOME)
        behind = self.switch_counts is not None and self.enc_pos <= self.switch_counts
        self.set_homed(False)
        self.homing_speed = speed_um_s or self.params.get(ParamId.HOME_SPEED_UM_S)
        self.homing_origin = self.profile.steps
        back_off = on_switch or behind
        self.homing_phase = HomingPhase.BACKOFF if back_off else HomingPhase.SEEK
        sign = 1 if back_off else -1
        self.profile.jog(
            sign * self.mech.speed_to_msteps(self.homing_speed), self.max_accel, self.stop_decel
        )
        self.state = State.HOMING

    @property
    def stop_decel(self) -> int:
        """STOP_DECEL_UM_S2 in profile units."""
        return self.mech.accel_to_msteps_per_tick(self.params.get(ParamId.STOP_DECEL_UM_S2))

    @property
    def max_accel(self) -> int:
        """MAX_ACCEL_UM_S2 in profile units."""
        return self.mech.accel_to_msteps_per_tick(self.params.get(ParamId.MAX_ACCEL_UM_S2))

    def start_session(self, host_capabilities: int) -> None:
        """A HELLO opened a session: samples still waiting go out, then batch only if agreed."""
        self._flush_batches()
        self.batching = bool(host_capabilities & self.capabilities & _BATCHED)
        self.quiet_probes = bool(host_capabilities & self.capabilities & _QUIET)
        self.quiet.clear()

    def set_stream(self, stream: int, rate_hz: int) -> None:
        """Switch a telemetry stream on at a rate, or off with 0."""
        if rate_hz == 0 and stream in self.batchers:
            self._flush_batch(stream)  # the samples taken so far are not held back
        self.stream_rates[stream] = rate_hz
        self.stream_acc[stream] = 0
        self.active_streams = [s for s in range(_N_STREAMS) if self.stream_rates[s]]

    # ---- boot -----------------------------------------------------------------------------

    def _boot(self) -> None:
        """Power-on or reset: fresh state, parameters from flash, a new boot id."""
        self._reboot_pending = False
        self.boots += 1
        self.boot_id = self.hal.random_u32() & 0xFFFF_FFFF
        self.state = State.BOOT
        self.faults = 0
        self.homed = False
        self.ticks = 0
        self._last_tx_tick = 0
        self.now_us = self.hal.micros()
        self.rx.reset()
        self.tx.reset()
        self.replies.clear()
        self.held.clear()
        self.next_cmd_seq = 0
        self.last_cmd_seq = 0
        self.profile = Profile()
        self.enc_raw = self.hal.encoder_read()
        self.enc_pos = 0
        self.velocity = 0
        self.switches = 0
        self.index_latch = None
        self.index_seen = False
        self.hello_seen = False
        self.frame_rx_us = self.now_us
        self.watchdog_armed = False
        self.last_rx_tick = 0
        self._frames_seen = self.counters.frames_in
        self.homing_phase = HomingPhase.SEEK
        self.homing_speed = 0
        self.homing_origin = 0
        self.switch_counts = None
        self.stream_rates = [0] * _N_STREAMS
        self.stream_acc = [0] * _N_STREAMS
        self.active_streams = []
        self.batching = False
        self.quiet_probes = False
        self.quiet.clear()
        for batcher in self.batchers.values():
            batcher.clear()
        self.hal.encoder_index_latch()  # discard a pulse from before the reset
        self.hal.drive_enable(True)
        self.state = State.IDLE
        if self.params.load(self.hal.flash_read()) is LoadResult.CORRUPT:
            self.latch_fault(Fault.FLASH, halt=True)
        # The state at boot is told by IDENTIFY; STATUS reports the changes after it.
        self._reported = (self.state, self.faults)

    # ---- the tick's parts -----------------------------------------------------------------

    def _read_sensors(self) -> None:
        """Extend the encoder counter, capture an index, read the switches, filter velocity."""
        hal = self.hal
        raw = hal.encoder_read()
        delta = _i32(raw - self.enc_raw)
        self.enc_raw = raw
        self.enc_pos += delta
        # Round to nearest, not floor: a floored shift settles up to 2^shift − 1 counts/s low.
        half = 1 << (VELOCITY_FILTER_SHIFT - 1)
        self.velocity += (delta * TICK_HZ - self.velocity + half) >> VELOCITY_FILTER_SHIFT
        latch = hal.encoder_index_latch()
        if latch is not None:
            # Position of the index pulse in the extended counter's coordinates.
            back = _i32(raw - latch)
            self.index_latch = self.enc_pos - back
            self.index_seen = True
        else:
            self.index_latch = None
        self.switches = hal.inputs_read() & _SWITCH_INPUTS
        mark = hal.mark_latch()
        if mark is not None and Stream.ENCODER in self.active_streams:
            back = _i32(raw - mark)
            self._flush_batch(int(Stream.ENCODER))  # the samples before the mark go first
            self.tx.send(RefMark(self.now_us, _i32(self.enc_pos - back)))

    def _receive(self, data: bytes, at_us: int) -> None:
        """Handle every complete frame in the RX ring; any valid frame feeds the watchdog.

        The HAL hands over the ring one delimiter at a time, each read stamped with the arrival
        of its last byte, so a frame completed by a read arrived at that read's stamp.
        """
        hal, rx = self.hal, self.rx
        while True:
            for frame in rx.feed(data):
                self.frame_rx_us = at_us
                commands.handle(self, *frame)
            if data[-1] != 0:
                break  # no delimiter at the end: that was the rest of the ring
            data, at_us = hal.link_read()
            if not data:
                break
        if self.counters.frames_in != self._frames_seen:
            self._frames_seen = self.counters.frames_in
            self.watchdog_armed = True
            self.last_rx_tick = self.ticks

    def _safety(self) -> None:
        """E-stop input, hard limits, following error and the host watchdog."""
        sw = self.switches
        if sw & _IN_ESTOP and self.state is not State.ESTOP:
            self.estop()
        vel = self.profile.vel
        if (vel > 0 and sw & _IN_LIMIT_MAX) or (vel < 0 and sw & _IN_LIMIT_MIN):
            self.latch_fault(Fault.HARD_LIMIT, halt=True)
        if self.state is not State.ESTOP:
            # Compared in units of 1/steps_per_rev count, so no division (and no rounding) is needed
            # whatever the microstepping and the encoder resolution.
            mech = self.mech
            err = (
                self.profile.steps * mech.encoder_counts_per_rev - self.enc_pos * mech.steps_per_rev
            )
            limit = self.params.values[ParamId.FOLLOWING_ERROR_COUNTS] * mech.steps_per_rev
            if (err > limit or -err > limit) and not self.faults & _F_FOLLOWING:
                self.latch_fault(Fault.FOLLOWING_ERROR, halt=True)
        if self.watchdog_armed:
            silence_ms = (self.ticks - self.last_rx_tick) * 1000 // TICK_HZ
            if silence_ms > self.params.values[ParamId.WATCHDOG_MS]:
                # From every running state, standing still included: a host that went silent
                # must be noticed before anything moves again (PROTOCOL §9).
                self.watchdog_armed = False
                if self.state in _WATCHDOG_STATES:
                    self.latch_fault(Fault.WATCHDOG, halt=False)

    def _homing(self) -> None:
        """Advance homing: switch, then index, then back onto the index."""
        phase = self.homing_phase
        if phase is HomingPhase.RETURN:
            return
        travel = abs(self.profile.steps - self.homing_origin)
        if travel > self.mech.um_to_steps(self.params.get(ParamId.HOMING_TRAVEL_UM)):
            self.latch_fault(Fault.HOMING_FAILED, halt=False)
            return
        if phase is HomingPhase.BACKOFF:
            past = self.switch_counts is None or self.enc_pos > self.switch_counts
            if not self.switches & _IN_HOME and past:
                self.homing_phase = HomingPhase.SEEK
                seek = -self.mech.speed_to_msteps(self.homing_speed)
                self.profile.jog(seek, self.max_accel, self.stop_decel)
        elif phase is HomingPhase.SEEK:
            if self.switches & _IN_HOME:
                self.homing_phase = HomingPhase.INDEX
                self.switch_counts = self.enc_pos
        elif self.index_latch is not None:
            self._latch_home(self.index_latch)

    def _latch_home(self, index_pos: int) -> None:
        """Make the index pulse's position HOME_OFFSET_UM and return onto it."""
        offset_um = self.params.get(ParamId.HOME_OFFSET_UM)
        delta = self.mech.um_to_counts(offset_um) - index_pos
        self.enc_pos += delta
        self.profile.shift(self.mech.counts_to_steps(self.enc_pos) - self.profile.steps)
        if self.switch_counts is not None:
            self.switch_counts += delta  # into the new frame, for the next HOME's back-off
        self.set_homed(True)
        self.homing_phase = HomingPhase.RETURN
        self.profile.move_to(
            self.mech.um_to_steps(offset_um),
            self.mech.speed_to_msteps(self.homing_speed),
            self.max_accel,
            self.stop_decel,
        )

    def _telemetry(self) -> None:
        """Emit each active stream when its rate accumulator rolls over."""
        acc = self.stream_acc
        for s in self.active_streams:
            acc[s] += self.stream_rates[s]
            if acc[s] >= TICK_HZ:
                acc[s] -= TICK_HZ
                self._emit(s)

    def _status(self) -> Status:
        """STATUS now; remembers what was reported so a change is noticed."""
        self._reported = (self.state, self.faults)
        target = self.mech.steps_to_um(self.profile.target_sub // SUB_PER_STEP)
        return Status(
            self.now_us,
            self.state,
            self.faults,
            self.inputs,
            _i32(self.position_um),
            _i32(target),
            self.last_cmd_seq,
        )

    def _emit(self, stream: int) -> None:
        """Queue one sample of a stream."""
        t = self.now_us
        if stream == Stream.ENCODER:
            flags = self.inputs | (_IN_INDEX if self.index_seen else 0)
            self.index_seen = False
            msg: object = EncoderSample(
                t, _i32(self.enc_pos), _i32(self.profile.steps), _i32(self.velocity), flags
            )
        elif stream == Stream.STATUS:
            msg = self._status()
        elif stream == Stream.RANGE:
            dist, quality = self.hal.range_read()
            msg = RangeSample(t, dist, quality)
        else:
            pan, tilt = self.hal.head_read()
            msg = HeadSample(t, _i32(pan), _i32(tilt))
        if self.batching and stream in self.batchers and self._batch_age_us(stream) > 0:
            assert isinstance(msg, EncoderSample | RangeSample | HeadSample)
            self._batch(stream, msg)
        else:
            self.tx.send(msg)

    # ---- quiet clock probes (PROTOCOL.md §8, R-QUIET-1) ------------------------------

    def clock_probe_arrived(self, rx_us: int) -> None:
        """A CLOCK_SYNC: in a quiet-probe session it starts or ends a hold (firmware.quiet)."""
        if self.quiet_probes:
            self.quiet.probe(rx_us)

    # ---- batched telemetry (firmware.batching) ---------------------------------------------

    def _batch_age_us(self, stream: int) -> int:
        """The stream's *_BATCH_AGE_MS in µs: how long a batch's oldest sample may wait."""
        return self.params.values[_BATCH_AGE_PARAMS[stream]] * 1000

    def _batch(self, stream: int, sample: Sample) -> None:
        """Add a sample to its stream's batch; queue the batches that are complete."""
        for batch in self.batchers[stream].add(sample):
            self.tx.send(batch)

    def _send_due_batches(self) -> None:
        """Queue each batch whose oldest sample has waited its age (latency stays bounded)."""
        for stream, batcher in self.batchers.items():
            batch = batcher.due(self.now_us, self._batch_age_us(stream))
            if batch is not None:
                self.tx.send(batch)

    def _flush_batch(self, stream: int) -> None:
        """Queue what one stream's batch holds."""
        batch = self.batchers[stream].flush()
        if batch is not None:
            self.tx.send(batch)

    def _flush_batches(self) -> None:
        """Queue every stream's waiting samples."""
        for stream in self.batchers:
            self._flush_batch(stream)
