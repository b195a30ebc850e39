"""Trapezoidal step generation in integer arithmetic, one call per 1 ms tick.

The commanded position is a sub-step fixed point (`SUB_PER_STEP` per microstep) and the
velocity is in milli-steps per second, so a tick advances the position by exactly the
velocity's value. Each tick picks the fastest velocity within one acceleration step of the
current one from which the profile can still stop at its target (`stop_distance`); this
online rule lands on the target without precomputing phases, re-plans when a command
changes the target mid-motion, and makes a jog toward a soft limit stop exactly on it.
"""

from __future__ import annotations

import enum
from math import isqrt

from firmware.config import SUB_PER_STEP

NO_LIMIT_SUB = 1 << 62  # the bound used before homing: hard limit switches guard instead


class Mode(enum.Enum):
    """What the profile generator is doing."""

    IDLE = 0  # standing still, no steps
    POSITION = 1  # ramping to a target position (MOVE_TO, JOG toward a limit, homing)
    STOP = 2  # ramping the velocity to zero (STOP, watchdog)


def stop_distance(v: int, a: int) -> int:
    """Sub-steps travelled at v this tick and then decelerating by a per tick to rest (v ≥ 0)."""
    n = v // a
    return (n + 1) * v - a * n * (n + 1) // 2


def fastest_stoppable(r: int, a: int) -> int:
    """Largest v ≥ 0 with stop_distance(v, a) ≤ r (r ≥ 0)."""
    n = isqrt(2 * r // a) if r > 0 else 0
    for _ in range(8):  # converges in one or two rounds; the bound only guards the loop
        v = (r + a * n * (n + 1) // 2) // (n + 1)
        if v >= (n + 1) * a:
            n += 1
        elif v < n * a:
            n -= 1
        else:
            return v
    return min(v, n * a)


class Profile:
    """The step generator: commanded position and velocity, the motion mode and its limits."""

    __slots__ = (
        "accel",
        "decel_floor",
        "hi_sub",
        "lo_sub",
        "mode",
        "pos_sub",
        "target_sub",
        "vel",
        "vmax",
    )

    def __init__(self) -> None:
        self.pos_sub = 0
        self.vel = 0  # milli-steps/s, signed
        self.mode = Mode.IDLE
        self.target_sub = 0
        self.vmax = 1
        self.accel = 1  # milli-steps/s per tick
        self.decel_floor = 1  # the least deceleration an unplanned stop uses
        self.lo_sub = -NO_LIMIT_SUB
        self.hi_sub = NO_LIMIT_SUB

    @property
    def steps(self) -> int:
        """Commanded position in whole microsteps."""
        return self.pos_sub // SUB_PER_STEP

    @property
    def moving(self) -> bool:
        """Whether steps may still be generated."""
        return self.mode is not Mode.IDLE

    def set_bounds(self, lo_steps: int | None, hi_steps: int | None) -> None:
        """Soft limits in microsteps (None: unbounded, before homing)."""
        self.lo_sub = -NO_LIMIT_SUB if lo_steps is None else lo_steps * SUB_PER_STEP
        self.hi_sub = NO_LIMIT_SUB if hi_steps is None else hi_steps * SUB_PER_STEP

    def move_to(self, target_steps: int, vmax: int, accel: int, decel_floor: int) -> None:
        """Ramp to a target in microsteps at most vmax (mstep/s), accel (mstep/s per tick)."""
        self.target_sub = max(self.lo_sub, min(self.hi_sub, target_steps * SUB_PER_STEP))
        self.vmax = max(1, vmax)
        self.accel = max(1, accel)
        self.decel_floor = max(self.accel, decel_floor)
        self.mode = Mode.POSITION

    def jog(self, velocity: int, accel: int, decel_floor: int) -> None:
        """Run at a signed velocity toward the soft limit in its direction (0 ramps down)."""
        if velocity == 0:
            self.stop(accel)
            return
        bound = self.hi_sub if velocity > 0 else self.lo_sub
        self.move_to(bound // SUB_PER_STEP, abs(velocity), accel, decel_floor)
        self.target_sub = bound

    def stop(self, decel: int) -> None:
        """Ramp the velocity to zero at decel (mstep/s per tick)."""
        self.accel = max(1, decel)
        self.mode = Mode.STOP if self.vel else Mode.IDLE

    def halt(self) -> None:
        """Stop generating steps at once (e-stop, hard limit, following error)."""
        self.vel = 0
        self.mode = Mode.IDLE

    def shift(self, delta_steps: int) -> None:
        """Re-reference the commanded position (homing) without moving."""
        self.pos_sub += delta_steps * SUB_PER_STEP
        self.target_sub += delta_steps * SUB_PER_STEP

    def tick(self) -> int:
        """Advance one tick; return the signed microsteps to issue."""
        mode = self.mode
        if mode is Mode.IDLE:
            return 0
        vel = self._stop_velocity() if mode is Mode.STOP else self._position_velocity()
        old = self.pos_sub
        new = old + vel
        # Last line of defence: the commanded position never leaves the soft window.
        if new > self.hi_sub and vel > 0:
            new, vel = max(old, self.hi_sub), 0
        elif new < self.lo_sub and vel < 0:
            new, vel = min(old, self.lo_sub), 0
        self.pos_sub = new
        self.vel = vel
        if vel == 0 and (mode is Mode.STOP or new == self.target_sub):
            self.mode = Mode.IDLE
        return new // SUB_PER_STEP - old // SUB_PER_STEP

    def _stop_velocity(self) -> int:
        """Velocity after one deceleration step toward zero."""
        vel, a = self.vel, self.accel
        if vel > 0:
            return max(0, vel - a)
        return min(0, vel + a)

    def _position_velocity(self) -> int:
        """Fastest signed velocity this tick from which the target is still reachable at rest."""
        rem = self.target_sub - self.pos_sub
        sgn = 1 if rem > 0 or (rem == 0 and self.vel < 0) else -1
        v = self.vel * sgn  # speed toward the target; negative while moving away
        r = rem * sgn
        a = self.accel
        best = fastest_stoppable(r, a) if r > 0 else 0
        upper = min(v + a, self.vmax) if v <= self.vmax else max(v - a, self.vmax)
        lower = v - a
        if best < lower:
            # Cannot stop in time at this acceleration (target or limit changed under us):
            # brake harder, never below the stop deceleration.
            lower = max(best, v - self.decel_floor)
        return max(lower, min(best, upper)) * sgn
