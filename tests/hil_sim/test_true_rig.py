"""The simulator's true rig: seeded tolerances, deterministic; any track of straights and arcs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hil_sim.rig_scenario import scenario_for_rig
from hil_sim.runner import Simulation
from hil_sim.true_rig import Tolerances, true_rig
from host.geometry.head import M_CR_DEFAULT
from host.geometry.transforms import R_to_rotvec, invert_T
from host.rig import JointCovariance, RigSpec, build_kinematics, loads_rig
from protocol import Inputs

OPEN_TRACK = """
[[track.segments]]
kind = "straight"
length_mm = 2000.0
[[track.segments]]
kind = "arc"
radius_mm = 800.0
angle_deg = 90.0
[[track.segments]]
kind = "straight"
length_mm = 1500.0
[track.placement]
matrix = [[1, 0, 0, 100], [0, 1, 0, -200], [0, 0, 1, 3500], [0, 0, 0, 1]]
[track.home]
value_mm = 150.0
"""


def test_same_seed_same_rig_other_seed_other_rig() -> None:
    nominal = RigSpec()
    a, b, c = true_rig(nominal, 4), true_rig(nominal, 4), true_rig(nominal, 5)
    assert a == b
    assert a != c
    assert a.head.m_cr != nominal.head.m_cr


def test_tolerances_are_of_the_stated_size() -> None:
    """Over many seeds, each drawn deviation has about its σ (and none is absurd)."""
    tol, nominal = Tolerances(), RigSpec()
    rigs = [true_rig(nominal, seed) for seed in range(200)]
    dm = np.array([(invert_T(M_CR_DEFAULT) @ r.head.m_cr.matrix)[:3, 3] for r in rigs])
    dw = np.array(
        [R_to_rotvec((invert_T(M_CR_DEFAULT) @ r.head.m_cr.matrix)[:3, :3]) for r in rigs]
    )
    fx = np.array([r.camera.intrinsics.get("fx") for r in rigs]) / nominal.camera.intrinsics.get(
        "fx"
    )
    u0 = np.array([r.camera.intrinsics.get("u0") for r in rigs])
    z = np.array([r.track.placement.matrix[2, 3] for r in rigs])
    assert dm.std() == pytest.approx(tol.m_cr_mm, rel=0.2)
    assert dw.std() == pytest.approx(tol.m_cr_rad, rel=0.2)
    assert (fx - 1).std() == pytest.approx(tol.focal_fraction, rel=0.2)
    assert u0.std() == pytest.approx(tol.principal_point_px, rel=0.2)
    assert z.std() == pytest.approx(tol.track_height_mm, rel=0.2)


def test_the_true_rig_keeps_no_calibration_covariance() -> None:
    joint = JointCovariance(("head.m_cr",), np.eye(6) * 1e-6)
    assert true_rig(dataclasses.replace(RigSpec(), covariance=joint), 3).covariance is None


def test_tolerances_off_is_the_nominal_rig() -> None:
    assert true_rig(RigSpec(), 3, Tolerances.off()) == RigSpec()


def test_a_closed_loop_stays_closed_and_an_open_track_gets_other_radii() -> None:
    loop = build_kinematics(true_rig(RigSpec(), 8)).track
    assert loop.closed
    nominal = loads_rig(OPEN_TRACK)
    truth = true_rig(nominal, 8)
    assert not build_kinematics(truth).track.closed
    assert truth.track.segments[1].radius_mm != nominal.track.segments[1].radius_mm
    assert abs(truth.track.segments[1].radius_mm - 800.0) < 5 * Tolerances().arc_radius_mm


def test_plant_runs_on_an_open_track_of_straights_and_arcs() -> None:
    truth = true_rig(loads_rig(OPEN_TRACK), 2)
    sc = scenario_for_rig(truth, seed=2)
    length = 3500.0 + 800.0 * math.pi / 2
    assert sc.track.length_mm == pytest.approx(build_kinematics(truth).track.length_mm)
    assert sc.track.length_mm == pytest.approx(length, abs=10.0)
    assert not sc.track.closed
    assert 0.0 < sc.track.limit_min_s_mm < sc.track.start_s_mm < sc.track.limit_max_s_mm < length
    sim = Simulation(sc)
    sim.plant.s_mm = 2400.0  # on the arc: the truth is the open track's geometry, not wrapped
    sim.step(1)
    s = sim.truth().s_wrapped_mm
    assert s == pytest.approx(sim.truth().s_mm)
    T = sim.trolley_pose()
    assert T[:3, 3] == pytest.approx(build_kinematics(truth).track.position(s), abs=1e-9)


def test_open_track_limit_switches_sit_inside_its_ends() -> None:
    sc = scenario_for_rig(loads_rig(OPEN_TRACK), seed=1)
    sim = Simulation(sc)
    sim.plant._anchor_s += sc.track.limit_max_s_mm + 1.0 - sim.plant.s_mm
    sim.step(1)
    assert sim.plant.switches() & int(Inputs.LIMIT_MAX)
