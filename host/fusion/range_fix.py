"""A rangefinder reading of a surveyed surface as an absolute fix of the track position.

With the head angles known, the distance the beam travels to a surveyed surface is a function
r(s) of the trolley's true arc length. Inverting it near the filter's prediction turns a reading
into s with a σ of (reading σ)/|∂r/∂s|. Only readings that pin s down are used: the beam must
meet a surface clearly (not grazing it, no other surface just behind where a small error would
land instead) and r must change briskly with s (a beam down at a level floor says nothing about
s; one along the track at an end wall says everything). Everything refused is counted by reason.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from host.geometry.head import Rig
from host.geometry.rangefinder import Hit, RangeScene, range_at

STEP_MM = 1.0  # finite-difference step for ∂r/∂s
MAX_PASSES = 4  # Gauss-Newton passes; a skip of a few teeth on a corner converges in three
# Below this step the slope at the prediction serves: on the tightest corner (1 m radius) the
# slope changes by well under 1 % per millimetre, so the step is right to a few µm.
RELINEARISE_MM = 1.0


@dataclass(frozen=True)
class RangeFixConfig:
    """How readings are weighed and which are refused."""

    noise_mm: float = 1.0  # σ of one reading
    head_sigma_rad: float = 1e-4  # σ of the head angles as read (resolution-limited)
    min_sensitivity: float = 0.3  # |∂r/∂s| below this: the reading says too little about s
    max_incidence_deg: float = 70.0  # beam to surface normal: steeper and the spot smears
    clearance_mm: float = 150.0  # the next surface along the beam must be at least this far on
    gate_mm: float = 60.0  # |s - prediction| beyond this is not this surface (3 teeth fit)


@dataclass
class RangeFixStats:
    """Readings turned into fixes, and the others by reason."""

    fixes: int = 0
    no_echo: int = 0
    no_surface: int = 0
    grazing: int = 0
    ambiguous: int = 0
    weak: int = 0
    out_of_gate: int = 0
    off_track: int = 0  # the inversion would leave an open track's ends
    unconverged: int = 0


@dataclass(frozen=True)
class RangeFix:
    """True arc length implied by one reading, its σ, and the surface it came from."""

    s_mm: float
    sigma_mm: float
    surface: str


@dataclass
class RangeFixer:
    """Inverts r(s) for readings of surveyed surfaces, near a predicted s."""

    rig: Rig
    scene: RangeScene
    config: RangeFixConfig = field(default_factory=RangeFixConfig)
    stats: RangeFixStats = field(default_factory=RangeFixStats)

    def fix(
        self, s_pred_mm: float, pan_rad: float, tilt_rad: float, distance_mm: float | None
    ) -> RangeFix | None:
        """The arc length at which the reading fits, or None (counted) when it cannot be used."""
        st, c = self.stats, self.config
        if distance_mm is None or not distance_mm > 0.0:
            st.no_echo += 1
            return None
        # Gauss-Newton from the prediction; a reading that agrees with it (the usual case)
        # needs one slope, a tooth skip on a corner a few more.
        s = s_pred_mm
        for _ in range(MAX_PASSES):
            slope = self._slope(s, pan_rad, tilt_rad)
            if slope is None:
                return None
            hit, drds = slope
            step = (distance_mm - hit.distance_mm) / drds
            s += step
            if abs(s - s_pred_mm) > c.gate_mm:
                st.out_of_gate += 1
                return None
            if abs(step) < RELINEARISE_MM:
                break
        else:
            st.unconverged += 1
            return None
        tan_inc = math.sqrt(max(0.0, 1.0 - hit.cos_incidence**2)) / hit.cos_incidence
        sigma_r = math.hypot(c.noise_mm, hit.distance_mm * tan_inc * c.head_sigma_rad)
        st.fixes += 1
        return RangeFix(s, sigma_r / abs(drds), self.scene.surfaces[hit.surface].name)

    def _slope(self, s_mm: float, pan: float, tilt: float) -> tuple[Hit, float] | None:
        """The hit at s and ∂r/∂s there, or None (counted) if the geometry is unusable."""
        st, c = self.stats, self.config
        track = self.rig.track
        if not track.closed and not STEP_MM <= s_mm <= track.length_mm - STEP_MM:
            st.off_track += 1
            return None
        hit = range_at(self.rig, self.scene, s_mm, pan, tilt)
        if hit is None:
            st.no_surface += 1
            return None
        if hit.cos_incidence < math.cos(math.radians(c.max_incidence_deg)):
            st.grazing += 1
            return None
        if hit.next_mm - hit.distance_mm < c.clearance_mm:
            st.ambiguous += 1
            return None
        ahead = range_at(self.rig, self.scene, s_mm + STEP_MM, pan, tilt)
        behind = range_at(self.rig, self.scene, s_mm - STEP_MM, pan, tilt)
        if ahead is None or behind is None or not ahead.surface == behind.surface == hit.surface:
            st.ambiguous += 1
            return None
        drds = (ahead.distance_mm - behind.distance_mm) / (2.0 * STEP_MM)
        if abs(drds) < c.min_sensitivity:
            st.weak += 1
            return None
        return hit, drds
