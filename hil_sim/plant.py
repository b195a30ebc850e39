"""The simulated machine: stepper, sprocket and chain, encoder, switches, head and rangefinder.

One `advance(steps)` call per controller tick integrates the rotor (a stepper's torque pulls
it toward the commanded angle with a sinusoidal, speed-limited torque, so too much speed or
acceleration makes it slip whole electrical cycles: missed steps), moves the chain through
the sprocket's polygon (chordal effect) with its elongation and any skipped teeth, and
updates the head. The encoder sits on the sprocket shaft: it sees missed steps but neither
elongation nor tooth skips, which is the drift the paper's registration suffers from.
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import random
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from hil_sim.scenario import Scenario
from protocol import Inputs

TWO_PI = 2.0 * math.pi
FIELD_SMOOTHING = 0.2  # per tick: the field speed's ~5 ms time constant
# Plain ints: read every tick, and IntFlag operators allocate.
_HOME, _LIMIT_MIN = int(Inputs.HOME), int(Inputs.LIMIT_MIN)
_LIMIT_MAX, _ESTOP_IN = int(Inputs.LIMIT_MAX), int(Inputs.ESTOP_IN)


@dataclass(frozen=True)
class Truth:
    """Ground truth at one instant (never visible to the firmware)."""

    time_s: float
    s_mm: float  # unwrapped arc length of the trolley
    s_wrapped_mm: float  # arc length on the track geometry (modulo the length on a loop)
    sprocket_rad: float
    lag_steps: float  # commanded minus actual sprocket angle, in microsteps
    tooth_skips: int  # net teeth the chain jumped (positive: trolley ahead of the sprocket)
    elongation: float
    pan_rad: float
    tilt_rad: float


@dataclass(frozen=True)
class MarkEvent:
    """The trolley passed an absolute reference mark."""

    time_s: float
    mark_s_mm: float
    encoder_abs_count: int  # the shaft's absolute count at that moment (not reset-relative)


class Plant:
    """The physical rig; state in SI-ish floats, mm and rad."""

    def __init__(self, scenario: Scenario, rng: random.Random) -> None:
        self.sc = scenario
        self.rng = rng
        st, ch, tr = scenario.stepper, scenario.chain, scenario.track
        self.step_rad = TWO_PI / (st.full_steps_per_rev * st.microsteps)
        self.rotor_teeth = st.full_steps_per_rev // 4  # one electrical cycle = 4 full steps
        self.counts_per_rev = 4 * scenario.encoder.lines
        self.tooth_rad = TWO_PI / ch.sprocket_teeth
        self.pitch_radius_mm = ch.pitch_mm / (2.0 * math.sin(math.pi / ch.sprocket_teeth))
        self.time_s = 0.0
        self.theta = rng.uniform(0.0, TWO_PI)  # sprocket angle; the index is at multiples of 2π
        self.theta_cmd = self.theta
        self.omega = 0.0
        self.field_omega = 0.0
        self.drive_on = True
        self.tooth_skips = 0
        self.elongation = ch.elongation
        self._anchor_s = tr.start_s_mm
        self._anchor_x = self._chain_x(self.theta)
        self.s_mm = tr.start_s_mm
        self.estop_pressed = False
        self.count_abs = self._count(self.theta)
        self.index_abs: int | None = None  # absolute count of the last index edge, until read
        self.pan = self.tilt = 0.0
        self.pan_target = self.tilt_target = 0.0
        self._head_moving = False
        self.marks = sorted(tr.reference_marks_mm)
        self._mark_slot = bisect.bisect(self.marks, self.s_mm)
        self.mark_events: list[MarkEvent] = []
        self.on_mark: Callable[[MarkEvent], None] | None = None
        # (time, s, pan, tilt) after each tick, kept once `keep_history` is called: a camera
        # exposes on its own clock, between the ticks, and `truth_at` looks its pose up there
        self._history: deque[tuple[float, float, float, float]] | None = None

    # ---- the hot path ---------------------------------------------------------------------

    def advance(self, steps: int, dt_s: float) -> None:
        """Integrate one tick of dt_s with `steps` microsteps commanded in it."""
        st = self.sc.stepper
        if steps:
            self.theta_cmd += steps * self.step_rad
        # The driver's current loop smooths the field's speed over a few ticks; damping
        # against the raw per-tick step count would inject the step quantisation as torque.
        field = self.field_omega
        field += (steps * self.step_rad / dt_s - field) * FIELD_SMOOTHING
        self.field_omega = field
        omega = self.omega
        torque = 0.0
        if self.drive_on:
            t_max = st.holding_torque_nm / (1.0 + abs(omega) / st.corner_speed_rad_s)
            lag = self.theta - self.theta_cmd
            torque = -t_max * math.sin(self.rotor_teeth * lag) - st.damping_nm_s * (omega - field)
            # Damping is the same windings' current: it cannot exceed the pull-out torque.
            torque = t_max if torque > t_max else -t_max if torque < -t_max else torque
        inv_j_dt = dt_s / st.inertia_kg_m2
        omega += torque * inv_j_dt
        # Coulomb friction as an impulse that can stop the rotor but never reverse it.
        f = st.friction_torque_nm * inv_j_dt
        omega = omega - f if omega > f else omega + f if omega < -f else 0.0
        self.omega = omega
        self.theta += omega * dt_s
        self.time_s += dt_s
        if abs(torque) > self.sc.chain.skip_torque_nm:
            self.inject_tooth_skip(-1 if torque > 0 else 1)
        self._update_track()
        if self._head_moving:
            self._slew_head(dt_s)
        if self._history is not None:
            self._history.append((self.time_s, self.s_mm, self.pan, self.tilt))

    def _update_track(self) -> None:
        """Chain and trolley position, encoder count and index edge, reference marks."""
        theta = self.theta
        stretch = 1.0 + self.elongation
        self.s_mm = self._anchor_s + (self._chain_x(theta) - self._anchor_x) * stretch
        count = math.floor(theta * self.counts_per_rev / TWO_PI)
        old = self.count_abs
        if count != old:
            cpr = self.counts_per_rev
            if count // cpr != old // cpr:
                self.index_abs = cpr * max(count // cpr, old // cpr)
            self.count_abs = count
        if self.marks:
            slot = bisect.bisect(self.marks, self.s_mm)
            if slot != self._mark_slot:
                self._pass_mark(min(slot, self._mark_slot))
                self._mark_slot = slot

    # ---- reads used by the board ----------------------------------------------------------

    def switches(self) -> int:
        """Closed switches as Inputs bits."""
        tr, s = self.sc.track, self.s_mm
        bits = _HOME if abs(s - tr.home_s_mm) <= tr.home_width_mm / 2 else 0
        if s <= tr.limit_min_s_mm:
            bits |= _LIMIT_MIN
        if s >= tr.limit_max_s_mm:
            bits |= _LIMIT_MAX
        if self.estop_pressed:
            bits |= _ESTOP_IN
        return bits

    def head_measure(self) -> tuple[float, float]:
        """Head angles as its encoders read them: quantised, with noise."""
        h = self.sc.head
        pan = self.pan + self.rng.gauss(0.0, h.noise_rad)
        tilt = self.tilt + self.rng.gauss(0.0, h.noise_rad)
        return _quantise(pan, h.resolution_rad), _quantise(tilt, h.resolution_rad)

    def range_measure(self) -> float | None:
        """Rangefinder distance in mm, or None when there is no valid echo."""
        rf = self.sc.rangefinder
        true = rf.target(self.s_mm, self.pan, self.tilt)
        if true is None or not rf.min_mm <= true <= rf.max_mm:
            return None
        return max(0.0, true + self.rng.gauss(0.0, rf.noise_mm))

    def set_head_target(self, pan_rad: float, tilt_rad: float) -> None:
        """New servo targets, quantised to the servo resolution."""
        res = self.sc.head.resolution_rad
        self.pan_target = _quantise(pan_rad, res)
        self.tilt_target = _quantise(tilt_rad, res)
        self._head_moving = True

    def set_drive(self, on: bool) -> None:
        """Energise or release the motor; energising locks the field onto the rotor."""
        if on and not self.drive_on:
            self.theta_cmd = self._nearest_equilibrium()
        self.drive_on = on

    # ---- fault injection ------------------------------------------------------------------

    def inject_tooth_skip(self, teeth: int = 1) -> None:
        """The chain jumps `teeth` teeth: the trolley moves by that many pitches, the shaft not."""
        self.tooth_skips += teeth
        self._anchor_s += teeth * self.sc.chain.pitch_mm * (1.0 + self.elongation)
        self._update_track()

    def inject_missed_steps(self, steps: int) -> None:
        """The shaft ends `steps` microsteps short of what was commanded (sign: of the motion)."""
        # Both rotor and field drop back: the rotor sits in a field cycle behind the one the
        # firmware's step count implies, which is exactly what a missed step leaves behind.
        self.theta_cmd -= steps * self.step_rad
        self.theta -= steps * self.step_rad
        self._update_track()

    def set_elongation(self, elongation: float) -> None:
        """Change the chain's stretch from now on, keeping the trolley where it is."""
        self._anchor_s = self.s_mm
        self._anchor_x = self._chain_x(self.theta)
        self.elongation = elongation

    def truth(self) -> Truth:
        """Ground truth now."""
        return Truth(
            self.time_s,
            self.s_mm,
            self.s_mm % self.sc.track.length_mm if self.sc.track.closed else self.s_mm,
            self.theta,
            (self.theta_cmd - self.theta) / self.step_rad,
            self.tooth_skips,
            self.elongation,
            self.pan,
            self.tilt,
        )

    @property
    def history_ticks(self) -> int:
        """How many ticks of pose history are kept (0: none)."""
        return 0 if self._history is None else self._history.maxlen or 0

    def keep_history(self, ticks: int) -> None:
        """From now on keep the trolley's and the head's pose over the last `ticks` ticks."""
        self._history = deque(self._history or (), maxlen=ticks)

    def truth_at(self, time_s: float) -> Truth | None:
        """Ground truth at a recent instant between two ticks, its pose interpolated (the
        sprocket's state, skips and stretch as now); None outside the kept history."""
        hist = self._history
        if not hist or not hist[0][0] <= time_s <= hist[-1][0]:
            return None
        i = bisect.bisect_left(hist, (time_s,))
        t1, s1, pan1, tilt1 = hist[i]
        t0, s0, pan0, tilt0 = hist[i - 1] if i > 0 else hist[i]
        w = (time_s - t0) / (t1 - t0) if t1 > t0 else 1.0
        s_mm = s0 + (s1 - s0) * w
        wrapped = s_mm % self.sc.track.length_mm if self.sc.track.closed else s_mm
        return dataclasses.replace(
            self.truth(), time_s=time_s, s_mm=s_mm, s_wrapped_mm=wrapped,
            pan_rad=pan0 + (pan1 - pan0) * w, tilt_rad=tilt0 + (tilt1 - tilt0) * w,
        )  # fmt: skip

    # ---- internals ------------------------------------------------------------------------

    def _chain_x(self, theta: float) -> float:
        """Chain travel in mm at sprocket angle theta, with the polygon effect."""
        pitch = self.sc.chain.pitch_mm
        if not self.sc.chain.chordal:
            return theta / self.tooth_rad * pitch
        k = math.floor(theta / self.tooth_rad + 0.5)
        return k * pitch + self.pitch_radius_mm * math.sin(theta - k * self.tooth_rad)

    def _count(self, theta: float) -> int:
        """Absolute quadrature count at angle theta."""
        return math.floor(theta * self.counts_per_rev / TWO_PI)

    def _nearest_equilibrium(self) -> float:
        """Field angle the rotor snaps to when the driver energises at its present phase."""
        cycle = TWO_PI / self.rotor_teeth
        return self.theta_cmd + round((self.theta - self.theta_cmd) / cycle) * cycle

    def _pass_mark(self, slot: int) -> None:
        """Record (and report) the crossing of one reference mark."""
        event = MarkEvent(self.time_s, self.marks[slot], self.count_abs)
        self.mark_events.append(event)
        if self.on_mark is not None:
            self.on_mark(event)

    def _slew_head(self, dt_s: float) -> None:
        """Move both axes toward their targets at the slew rate."""
        lim = self.sc.head.slew_rad_s * dt_s
        self.pan += max(-lim, min(lim, self.pan_target - self.pan))
        self.tilt += max(-lim, min(lim, self.tilt_target - self.tilt))
        self._head_moving = self.pan != self.pan_target or self.tilt != self.tilt_target


def _quantise(x: float, res: float) -> float:
    """Round to a multiple of res."""
    return round(x / res) * res
