"""Plant physics: encoder scale, chordal effect, elongation, tooth skips, missed steps, stalls."""

from __future__ import annotations

import math
import random

import pytest

from hil_sim.plant import Plant
from hil_sim.scenario import ChainConfig, Scenario, StepperConfig

DT_S = 1e-3
PITCH_MM = 12.7
TEETH = 20
STEPS_PER_REV = 3200
COUNTS_PER_MM = 4000 / (TEETH * PITCH_MM)


def plant(**chain: float | bool) -> Plant:
    """A plant with a given chain configuration."""
    sc = Scenario(chain=ChainConfig(**chain))  # type: ignore[arg-type]
    return Plant(sc, random.Random(5))


def drive(p: Plant, steps_per_tick: float, ticks: int, ramp_ticks: int = 300) -> int:
    """Ramp to a step rate, hold it, ramp down (as a profile would); return steps issued."""
    acc = 0.0
    issued = 0
    rates = [steps_per_tick * min(1.0, (i + 1) / ramp_ticks) for i in range(ramp_ticks)]
    rates += [steps_per_tick] * ticks + rates[::-1]
    for rate in rates:
        acc += rate
        n = int(acc)
        acc -= n
        issued += n
        p.advance(n, DT_S)
    for _ in range(300):
        p.advance(0, DT_S)
    return issued


def test_encoder_counts_per_mm_equal_the_theory() -> None:
    p = plant()
    s0, c0 = p.s_mm, p.count_abs
    steps = drive(p, 4, 7700)  # about 32 000 steps = 10 turns = 2540 mm
    counts = p.count_abs - c0
    travel_mm = p.s_mm - s0
    assert counts == pytest.approx(steps * 4000 / STEPS_PER_REV, abs=3)
    assert travel_mm == pytest.approx(steps * TEETH * PITCH_MM / STEPS_PER_REV, abs=0.3)
    assert counts / travel_mm == pytest.approx(COUNTS_PER_MM, rel=2e-4)


def chain_ratio(p: Plant) -> float:
    """min/max of chain travel per sprocket angle while turning steadily."""
    drive(p, 2, 0)
    ratios = []
    s, th = p.s_mm, p.theta
    for _ in range(3000):
        p.advance(2, DT_S)
        if abs(p.theta - th) > 1e-6:
            ratios.append((p.s_mm - s) / (p.theta - th))
        s, th = p.s_mm, p.theta
    return min(ratios) / max(ratios)


def test_chordal_effect_modulates_chain_speed_by_cos_pi_over_z() -> None:
    # Chain travel per sprocket angle is R·cos(φ) for φ within ±π/z of a tooth.
    assert chain_ratio(plant()) == pytest.approx(math.cos(math.pi / TEETH), abs=2e-3)
    assert chain_ratio(plant(chordal=False)) == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("turns", [2, 4, 8])
def test_elongation_error_grows_linearly_with_travel(turns: int) -> None:
    p = plant(elongation=0.005)
    s0, c0 = p.s_mm, p.count_abs
    drive(p, 4, turns * STEPS_PER_REV // 4 - 300)
    encoder_mm = (p.count_abs - c0) / COUNTS_PER_MM
    error_mm = (p.s_mm - s0) - encoder_mm
    assert error_mm == pytest.approx(0.005 * encoder_mm, abs=0.2)


def test_tooth_skip_moves_trolley_one_pitch_not_the_encoder() -> None:
    p = plant()
    drive(p, 4, 1000)
    s, c = p.s_mm, p.count_abs
    p.inject_tooth_skip(-1)
    assert p.count_abs == c
    assert p.s_mm - s == pytest.approx(-PITCH_MM)
    assert p.truth().tooth_skips == -1


def test_missed_steps_are_seen_by_the_encoder() -> None:
    p = plant()
    drive(p, 4, 1000)
    s, c = p.s_mm, p.count_abs
    p.inject_missed_steps(64)
    drive(p, 0, 10)
    assert c - p.count_abs == pytest.approx(80, abs=2)  # 64 microsteps = 80 counts
    assert s - p.s_mm == pytest.approx(64 * 254 / 3200, abs=0.5)


def test_excess_acceleration_stalls_the_motor() -> None:
    p = Plant(Scenario(stepper=StepperConfig()), random.Random(1))
    c0 = p.count_abs
    # 0 → 2 m/s in 50 ms (40 m/s²): far beyond the pull-out torque.
    commanded = drive(p, 25, 500, ramp_ticks=50)
    moved_steps = (p.count_abs - c0) * 3200 / 4000
    assert moved_steps < 0.5 * commanded
    assert abs(p.truth().lag_steps) > 1000


def test_moderate_motion_does_not_lose_steps() -> None:
    p = plant()
    c0 = p.count_abs
    commanded = drive(p, 6, 2000, ramp_ticks=1000)  # 0.48 m/s reached at 0.48 m/s²
    assert (p.count_abs - c0) == pytest.approx(commanded * 5 / 4, abs=4)


def test_drive_off_coasts_to_rest_under_friction() -> None:
    p = plant()
    drive(p, 4, 500)
    for _ in range(300):
        p.advance(4, DT_S)
    p.set_drive(False)
    for _ in range(2000):
        p.advance(0, DT_S)
    assert p.omega == 0.0
