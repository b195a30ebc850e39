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

from host.fusion.chain_filter import ChainFilterConfig
from host.fusion.range_fix import RangeFixConfig, RangeFixer, Systematic
from host.geometry.head import Rig
from host.rig import RigSpec, build_scene


def marks_sigma_mm(spec: RigSpec) -> float:
    """σ of a listed mark relative to the controller's zero."""
    return math.hypot(spec.track.marks.sigma_mm, spec.track.home.sigma)


def chain_config(spec: RigSpec, pitch_mm: float) -> ChainFilterConfig:
    """The chain filter with the rig file's marks σ, and the range model's parameters (their
    σ from the rig file) as states when it lists surveyed surfaces the fixes rest on."""
    cov = Systematic.of(spec).covariance
    bias = cov if spec.hall.surfaces and np.any(cov) else None  # none for an exact model
    return ChainFilterConfig(
        chain_pitch_mm=pitch_mm, reference_sigma_mm=marks_sigma_mm(spec), bias_cov=bias
    )


def ranger(spec: RigSpec, rig: Rig) -> RangeFixer | None:
    """Fixes on the rig file's surveyed surfaces (None when it lists none), with their σ."""
    scene = build_scene(spec)
    if scene is None:
        return None
    config = RangeFixConfig(noise_mm=spec.rangefinder.noise_mm)
    return RangeFixer(rig, scene, config, systematic=Systematic.of(spec))
