"""The demo's rigs: the nominal description the host starts from and the true rig it never sees.

`orbitar demo` uses the paper's rig in a 12 m × 9 m hall with surveyed walls and reference marks
every metre; `orbitar demo --rig FILE` any other rig description. With tolerances on, the
simulator builds the true rig off the description by seeded installation tolerances
(`hil_sim.true_rig`); with them off the true rig is the description itself (the demo before
issue 11, when the host was handed the simulator's own calibration).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hil_sim.rig_scenario import scenario_for_rig, start_position_mm
from hil_sim.scenario import Scenario
from hil_sim.true_rig import Tolerances, true_rig
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import Wireframe, load_model, manipulator_wireframe
from host.geometry.rangefinder import hall_walls
from host.geometry.transforms import FloatArray, make_T
from host.rig import (
    HallSpec,
    Marks,
    Pose6,
    RigSpec,
    SurfaceSpec,
    build_camera,
    build_kinematics,
    load_rig,
    travel_limits_mm,
    workpiece_pose,
)
from host.rig.schema import SURVEY_SIGMA_MM

BUILTIN_MODEL = "builtin:manipulator"
MARK_SPACING_MM = 1000.0  # reference marks along the track (magnets under a hall sensor)
FIRST_MARK_MM = 400.0  # just past the home switch, so the chain scale is learnt early
LAST_MARK_BEFORE_END_MM = 80.0
HALL_X_MM = (-6000.0, 6000.0)  # a 12 m × 9 m hall around the runway (centred on the origin)
HALL_Y_MM = (-4500.0, 4500.0)
HOME_SWITCH_MM = 150.0  # where the runway's home switch is mounted
WORKPIECE_W = (-300.0, -300.0, 0.0)  # the robot's base on the floor, inside the runway
LOOK_AHEAD_TILT_RAD = math.pi / 2  # the drift loop looks along the track at the end walls


def paper_demo_rig() -> RigSpec:
    """The paper's rig in a hall whose walls are surveyed, with reference marks every metre."""
    base = RigSpec()
    marks = tuple(np.arange(FIRST_MARK_MM, base.track.length_mm - 80.0, MARK_SPACING_MM).tolist())
    surfaces = tuple(
        SurfaceSpec(s.name, s.point_w, s.normal_w, 0.0, SURVEY_SIGMA_MM)
        for s in hall_walls(x_mm=HALL_X_MM, y_mm=HALL_Y_MM)
    )
    home = dataclasses.replace(base.track.home, value=HOME_SWITCH_MM)
    frame = Pose6(
        make_T(np.eye(3), WORKPIECE_W),
        base.workpiece.frame.sigma_rad,
        base.workpiece.frame.sigma_mm,
    )
    return dataclasses.replace(
        base,
        name="paper runway in a surveyed hall",
        track=dataclasses.replace(base.track, marks=Marks(marks), home=home),
        hall=HallSpec(surfaces),
        head=dataclasses.replace(base.head, tilt_max_rad=LOOK_AHEAD_TILT_RAD),
        workpiece=dataclasses.replace(base.workpiece, frame=frame),
    )


def exact(spec: RigSpec) -> RigSpec:
    """The description as the truth: every value it hands over with σ 0.

    Only the home stays as it is: the demo surveys the controller's zero at every run, and the
    head's read noise is the sensor's, not a calibration's.
    """

    def pose(p: Pose6) -> Pose6:
        return Pose6(p.matrix, provenance=p.provenance)

    track, cam = spec.track, spec.camera
    intrinsics = dataclasses.replace(
        cam.intrinsics, sigma=(0.0,) * len(cam.intrinsics.sigma), covariance=None
    )
    return dataclasses.replace(
        spec,
        covariance=None,
        track=dataclasses.replace(
            track,
            placement=pose(track.placement),
            marks=dataclasses.replace(track.marks, sigma_mm=0.0),
            arc_radius_sigma_mm=0.0,
        ),
        hall=dataclasses.replace(
            spec.hall,
            surfaces=tuple(dataclasses.replace(s, sigma_mm=0.0) for s in spec.hall.surfaces),
        ),
        head=dataclasses.replace(spec.head, m_cr=pose(spec.head.m_cr)),
        rangefinder=dataclasses.replace(spec.rangefinder, mount=pose(spec.rangefinder.mount)),
        camera=dataclasses.replace(
            cam, intrinsics=intrinsics, latency=dataclasses.replace(cam.latency, sigma=0.0)
        ),
        workpiece=dataclasses.replace(spec.workpiece, frame=pose(spec.workpiece.frame)),
    )


def model_of(spec: RigSpec) -> Wireframe:
    """The workpiece model the rig names."""
    path = spec.workpiece.model
    return manipulator_wireframe() if path == BUILTIN_MODEL else load_model(path)


@dataclass(frozen=True)
class DemoRigs:
    """The nominal rig (the host's start), the true rig (the simulator's) and the host's now."""

    nominal: RigSpec
    truth: RigSpec
    host: RigSpec
    tolerances: bool

    @classmethod
    def make(cls, rig_path: Path | None, seed: int, tolerances: bool) -> DemoRigs:
        """Read the rig file (or take the paper's), draw the true rig for this seed.

        Without tolerances the host is handed the true rig, and told so: its rig file gives
        the values it was handed σ 0 (`exact`), or its drift filter and error budget would
        weigh them by a datasheet's σ they do not have.
        """
        nominal = paper_demo_rig() if rig_path is None else load_rig(rig_path)
        tol = Tolerances() if tolerances else Tolerances.off()
        host = nominal if tolerances else exact(nominal)
        return cls(nominal, true_rig(nominal, seed, tol), host, tolerances)

    def scenario(self, seed: int) -> Scenario:
        """The plant on the true rig."""
        return scenario_for_rig(self.truth, seed)

    def host_kinematics(self) -> Rig:
        """What the host computes poses with (nominal until commissioning replaced it)."""
        return build_kinematics(self.host)

    def true_kinematics(self) -> Rig:
        """What the simulator renders with (scoring only)."""
        return build_kinematics(self.truth)

    def host_camera(self) -> CameraModel:
        """The host's camera model."""
        return build_camera(self.host)

    def true_camera(self) -> CameraModel:
        """The simulator's lens (scoring and rendering only)."""
        return build_camera(self.truth)

    def host_workpiece(self) -> FloatArray:
        """Where the host believes the workpiece is (T_w_p)."""
        return workpiece_pose(self.host)

    def true_workpiece(self) -> FloatArray:
        """Where the workpiece truly is (rendering and scoring only)."""
        return workpiece_pose(self.truth)

    def start_s_mm(self) -> float:
        """Where the trolley stands at power-on (the first observation point)."""
        return start_position_mm(self.host)

    def home_switch_mm(self) -> float:
        """Where the drawing puts the home switch: the description's home before any survey.

        A survey (commissioning) replaces the rig file's home with the controller's zero, the
        first index pulse past the switch, up to a sprocket turn away from it.
        """
        return self.nominal.track.home.value

    def travel_mm(self) -> tuple[float, float]:
        """The travel between the limit switches, as the host's description has it."""
        return travel_limits_mm(self.host.track)
