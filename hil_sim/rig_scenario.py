"""A simulation scenario from a rig description: the plant on the rig's (true) track.

`orbitar sim --rig FILE` and `orbitar demo --rig FILE` describe the rig they simulate with the
same schema the daemon reads; this module turns the true rig (the file, or the file plus seeded
tolerances from `hil_sim.true_rig`) into the plant's scenario: track geometry and length, limit
switches, home switch, reference marks, and a rangefinder that reads the true surveyed surfaces
through the true mount.
"""

from __future__ import annotations

from hil_sim.scenario import ChainConfig, RangefinderConfig, Scenario, TrackConfig
from hil_sim.surveyed_range import surveyed_target
from host.geometry.rangefinder import RangeScene, Surface
from host.rig import RigSpec, build_kinematics, build_scene, travel_limits_mm

DEFAULT_START_S_MM = 500.0  # where the trolley stands at power-on (the paper rig's scenario)
START_MARGIN_MM = 200.0  # power-on position beyond the home switch and inside the limits
FLOOR = Surface("floor", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))


def start_position_mm(truth: RigSpec) -> float:
    """Where the trolley stands at power-on: a little past the home switch, inside the travel."""
    lo, hi = travel_limits_mm(truth.track)
    wanted = max(DEFAULT_START_S_MM, truth.track.home.value + START_MARGIN_MM)
    return min(max(wanted, lo + START_MARGIN_MM), hi - START_MARGIN_MM)


def scenario_for_rig(
    truth: RigSpec,
    seed: int,
    elongation: float = 0.0,
    start_s_mm: float | None = None,
) -> Scenario:
    """The scenario whose plant is the rig `truth` (which the host never sees)."""
    kin = build_kinematics(truth)
    lo, hi = travel_limits_mm(truth.track)
    track = TrackConfig(
        length_mm=kin.track.length_mm,
        closed=kin.track.closed,
        path=kin.track,
        start_s_mm=start_position_mm(truth) if start_s_mm is None else start_s_mm,
        home_s_mm=truth.track.home.value,
        limit_min_s_mm=lo,
        limit_max_s_mm=hi,
        reference_marks_mm=truth.track.marks.s_mm,
    )
    scene = build_scene(truth) or RangeScene((FLOOR,))  # without a survey, the floor is there
    rf = truth.rangefinder
    rangefinder = RangefinderConfig(
        noise_mm=rf.noise_mm, min_mm=rf.min_mm, max_mm=rf.max_mm, target=surveyed_target(kin, scene)
    )
    return Scenario(
        seed=seed,
        chain=ChainConfig(
            sprocket_teeth=truth.track.chain.sprocket_teeth,
            pitch_mm=truth.track.chain.pitch_mm,
            elongation=elongation,
        ),
        track=track,
        rangefinder=rangefinder,
    )
