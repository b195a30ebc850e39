"""Scenario configuration: the simulated rig, with the paper's rig as the defaults.

Lengths in mm, angles in rad, time in s, as everywhere in Orbitar; names carry other units.
The track position `s_mm` is the trolley's unwrapped arc length along the track: on a closed
loop the cable carrier lets it go round only once, so the hard limit switches sit at the two
ends of that unwrapped travel; on an open track they sit near its two ends. The track's shape
is `TrackConfig.path` (host.geometry.track, the one track module; None: the paper's runway);
`hil_sim.rig_scenario` builds a whole scenario from a (true) rig description.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from firmware.config import Mechanics

if TYPE_CHECKING:
    from host.geometry.track import Track

# Paper §5: 6 m × 3 m rounded rectangle, corner radius 1 m.
RUNWAY_LENGTH_MM = 2 * (6000 - 2000) + 2 * (3000 - 2000) + 2 * math.pi * 1000

RangeTarget = Callable[[float, float, float], float | None]
"""(trolley s_mm, pan_rad, tilt_rad) → true distance along the beam in mm, or None (no echo)."""


@dataclass
class StepperConfig:
    """Stepper motor and driver: a sinusoidal torque-vs-lag model with a pull-out curve."""

    full_steps_per_rev: int = 200
    microsteps: int = 16
    holding_torque_nm: float = 1.2
    # Pull-out torque falls as T_hold / (1 + ω/ω_c): back-EMF eats the driver's voltage.
    corner_speed_rad_s: float = 8.0
    damping_nm_s: float = 0.3  # driver damping of the rotor's oscillation (ζ ≈ 0.2)
    inertia_kg_m2: float = 0.0082  # rotor + sprocket + 5 kg trolley reflected through r ≈ 40 mm
    friction_torque_nm: float = 0.2  # rolling resistance of trolley and chain, at the sprocket


@dataclass
class ChainConfig:
    """Drive sprocket and roller chain."""

    sprocket_teeth: int = 20
    pitch_mm: float = 12.7  # ISO 08B
    elongation: float = 0.0  # worn chain: 0.005 = 0.5 % longer pitch
    chordal: bool = True  # polygon effect of the sprocket on the chain speed
    skip_torque_nm: float = 2.5  # tooth jump under a load above this (above the motor's reach)


@dataclass
class EncoderConfig:
    """Sprocket shaft encoder."""

    lines: int = 1000  # ×4 quadrature counts per turn


@dataclass
class TrackConfig:
    """Where the trolley is and what switches it meets along the unwrapped arc length."""

    length_mm: float = RUNWAY_LENGTH_MM
    closed: bool = True  # a loop: the geometry wraps s modulo length_mm; open: s as it is
    path: Track | None = None  # the true track geometry; None: the paper's runway
    start_s_mm: float = 500.0
    home_s_mm: float = 150.0
    home_width_mm: float = 10.0
    limit_min_s_mm: float = -400.0
    limit_max_s_mm: float = RUNWAY_LENGTH_MM + 500.0
    reference_marks_mm: tuple[float, ...] = ()  # absolute marks, for drift correction


@dataclass
class HeadConfig:
    """Pan/tilt head: slew-rate limited servos with finite resolution and read noise."""

    slew_rad_s: float = 1.0
    resolution_rad: float = 1e-4
    noise_rad: float = 2e-5


def _floor_target(s_mm: float, pan_rad: float, tilt_rad: float) -> float | None:
    """Default target: a floor 4 m below the head, beam straight down at pan = tilt = 0."""
    c = math.cos(pan_rad) * math.cos(tilt_rad)
    return 4000.0 / c if c > 0.05 else None


@dataclass
class RangefinderConfig:
    """Laser rangefinder: noise, measuring range and the true-distance callback."""

    noise_mm: float = 1.0
    min_mm: float = 50.0
    max_mm: float = 40_000.0
    target: RangeTarget = _floor_target


@dataclass
class ClockConfig:
    """The MCU's crystal: offset of its µs counter at power-on and its frequency error."""

    offset_us: int = 123_456
    drift_ppm: float = 20.0


@dataclass
class Scenario:
    """Everything that defines a simulated run; same scenario and seed, same run."""

    seed: int = 1
    stepper: StepperConfig = field(default_factory=StepperConfig)
    chain: ChainConfig = field(default_factory=ChainConfig)
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    track: TrackConfig = field(default_factory=TrackConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    rangefinder: RangefinderConfig = field(default_factory=RangefinderConfig)
    clock: ClockConfig = field(default_factory=ClockConfig)
    flash_path: str | None = None  # parameter sector in a file; None keeps it in memory

    def firmware_build(self) -> Mechanics:
        """The firmware built for this drive (its nominal chain pitch: the stretch it cannot
        know); IDENTIFY reports it to the host as a real controller's build does."""
        return Mechanics(
            encoder_counts_per_rev=4 * self.encoder.lines,
            steps_per_rev=self.stepper.full_steps_per_rev * self.stepper.microsteps,
            sprocket_teeth=self.chain.sprocket_teeth,
            chain_pitch_um=round(self.chain.pitch_mm * 1000.0),
        )
