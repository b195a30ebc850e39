"""The chain filter's absolute references as the rig file describes them, with its σ.

A reference is used relative to the controller's zero: the feed adds the rig file's home to the
encoder's millimetres. A mark's listed arc length and the home were measured apart (the drawing
or a marks survey; the home survey), so a mark relative to the zero carries both σ. Rangefinder
fixes rest on the range model (mount, track placement, surveyed surfaces), whose parameters the
chain filter holds as states with the rig file's σ; fixes are taken relative to the zero's
survey once one is anchored (`RangeFixer.anchor_at`).
"""

from __future__ import annotations

import math

import numpy as np

from host.fusion.chain_filter import HOMING_REPEATABILITY_MM, ChainFilterConfig
from host.fusion.range_fix import RangeFixConfig, RangeFixer, Systematic
from host.geometry.head import Rig
from host.rig import RigSpec, build_scene


def marks_sigma_mm(spec: RigSpec) -> float:
    """σ of a listed mark relative to the controller's zero."""
    return math.hypot(spec.track.marks.sigma_mm, spec.track.home.sigma)


def chain_config(spec: RigSpec, pitch_mm: float) -> ChainFilterConfig:
    """The chain filter with the rig file's marks σ, and the range model's parameters (their
    σ from the rig file) as states when it lists surveyed surfaces the fixes rest on.

    The offset's prior is the homing's repeatability and the home's σ together: a reference
    is taken relative to the rig file's home, so an error in it is an offset the filter must
    be free to learn. With the prior at the repeatability alone, a zero known to ±6 mm (a
    first survey through a drawing's rig) left a fix half a pitch off either refused, so the
    pose kept the zero's error, or taken for a tooth skip, which moved it by the rest.
    """
    cov = Systematic.of(spec).covariance
    bias = cov if spec.hall.surfaces and np.any(cov) else None  # none for an exact model
    return ChainFilterConfig(
        chain_pitch_mm=pitch_mm,
        offset_sigma0_mm=math.hypot(HOMING_REPEATABILITY_MM, spec.track.home.sigma),
        reference_sigma_mm=marks_sigma_mm(spec),
        bias_cov=bias,
    )


def ranger(spec: RigSpec, rig: Rig) -> RangeFixer | None:
    """Fixes on the rig file's surveyed surfaces (None when it lists none), with their σ."""
    scene = build_scene(spec)
    if scene is None:
        return None
    config = RangeFixConfig(noise_mm=spec.rangefinder.noise_mm)
    return RangeFixer(rig, scene, config, systematic=Systematic.of(spec))
