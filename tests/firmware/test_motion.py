"""The integer trapezoidal profile generator, on its own."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from firmware.config import MECHANICS, SUB_PER_STEP
from firmware.motion import Profile, fastest_stoppable, stop_distance

MAX_TICKS = 200_000


def run(p: Profile) -> tuple[int, int, list[int]]:
    """Tick until idle: (ticks, steps issued, velocities)."""
    ticks = total = 0
    vels = []
    while p.moving and ticks < MAX_TICKS:
        total += p.tick()
        vels.append(p.vel)
        ticks += 1
    return ticks, total, vels


@given(st.integers(0, 10**9), st.integers(1, 10**6))
def test_fastest_stoppable_is_the_exact_inverse(r: int, a: int) -> None:
    v = fastest_stoppable(r, a)
    assert stop_distance(v, a) <= r < stop_distance(v + 1, a)


@settings(max_examples=60, deadline=None)
@given(
    target=st.integers(-5_000, 5_000),
    vmax=st.integers(200_000, 30_000_000),
    accel=st.integers(50, 100_000),
)
def test_move_lands_on_target_within_speed_and_accel(target: int, vmax: int, accel: int) -> None:
    p = Profile()
    p.move_to(target, vmax, accel, accel)
    ticks, total, vels = run(p)
    assert ticks < MAX_TICKS
    assert total == target
    assert p.pos_sub == target * SUB_PER_STEP
    assert max(abs(v) for v in vels or [0]) <= vmax
    prev = 0
    for v in vels[:-1]:  # the last tick may snap onto the target
        assert abs(v - prev) <= accel
        prev = v


def test_paper_speed_move_takes_the_trapezoid_time() -> None:
    p = Profile()
    speed = MECHANICS.speed_to_msteps(100_000)  # 0.1 m/s, the paper's camera speed
    accel = MECHANICS.accel_to_msteps_per_tick(500_000)
    p.move_to(12_598, speed, accel, accel)  # 1 m
    ticks, _, _ = run(p)
    expected_s = 1.0 / 0.1 + 0.1 / 0.5  # cruise + one ramp's worth
    assert abs(ticks / 1000 - expected_s) < 0.02


@settings(max_examples=60, deadline=None)
@given(st.integers(-10_000, 10_000), st.integers(-10_000, 10_000))
def test_retarget_against_motion_never_leaves_bounds(first: int, second: int) -> None:
    p = Profile()
    p.set_bounds(-10_000, 10_000)
    p.move_to(first, 20_000_000, 5_000, 20_000)
    for _ in range(300):
        p.tick()
    p.move_to(second, 20_000_000, 500, 20_000)  # much gentler: may have to brake harder
    while p.moving:
        p.tick()
        assert p.lo_sub <= p.pos_sub <= p.hi_sub
    assert p.steps == second


def test_jog_stops_on_the_bound_and_stop_ramps_down() -> None:
    p = Profile()
    p.set_bounds(-1_000, 5_000)
    p.jog(10_000_000, 20_000, 20_000)
    _, total, _ = run(p)
    assert total == 5_000
    p.jog(-10_000_000, 20_000, 20_000)
    for _ in range(200):
        p.tick()
    v = p.vel
    p.stop(50_000)
    ticks, _, _ = run(p)
    assert ticks == -(-abs(v) // 50_000)
    assert p.vel == 0
