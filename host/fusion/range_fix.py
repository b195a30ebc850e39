"""A rangefinder reading of a surveyed surface as an absolute fix of the track position.

With the head angles known, the distance the beam travels to a surveyed surface is a function
r(s) of the trolley's true arc length. Inverting it near the filter's prediction turns a reading
into s with a σ of (reading σ)/|∂r/∂s|. Only readings that pin s down are used: the beam must
meet a surface clearly (not grazing it, no other surface just behind where a small error would
land instead) and r must change briskly with s (a beam down at a level floor says nothing about
s; one along the track at an end wall says everything). Everything refused is counted by reason.

The model itself is only known as well as the rig file says: the mount, the track's placement
and each surface's survey carry a σ. Their error is a bias shared by every reading from the
same geometry, which no number of readings averages away, so it is kept apart (`Systematic`)
from the reading's noise: a fix carries its sensitivity to those parameters (`gradient`), and
the chain filter holds them as states (host.fusion.chain_filter) and weighs every fix with the
correlation it has with the others. The controller's zero was surveyed through the same model
(`anchor_at`): a fix is taken relative to that survey, so the part of the bias both share (the
same wall, the same aim) cancels, and its gradient is the difference of the two. Nothing is
refused for its bias: a fix from a geometry the rig file knows poorly (an uncalibrated mount on
a corner) only counts for less, and a surface first met later (the side wall past a corner,
surveyed apart from the end wall) is learnt against the dead reckoning as its fixes arrive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from host.geometry.head import Rig
from host.geometry.rangefinder import Hit, RangeScene, range_at
from host.geometry.transforms import FloatArray
from host.rig import RigSpec

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


@dataclass(frozen=True)
class Systematic:
    """The rig file's σ of what a reading's prediction rests on: the mount's and the track
    placement's covariance (local δ, 6×6 each) and each surface's survey σ (scene order)."""

    mount_cov: FloatArray
    placement_cov: FloatArray
    surface_sigma_mm: FloatArray

    @classmethod
    def of(cls, spec: RigSpec) -> Systematic:
        """From the rig file the host computes with."""
        sigma = np.array([s.sigma_mm for s in spec.hall.surfaces], dtype=np.float64)
        return cls(spec.rangefinder.mount.cov(), spec.track.placement.cov(), sigma)

    @cached_property
    def covariance(self) -> FloatArray:
        """Over (mount δ, placement δ, surface offsets): the blocks are surveyed apart."""
        n = 12 + len(self.surface_sigma_mm)
        out = np.zeros((n, n))
        out[:6, :6], out[6:12, 6:12] = self.mount_cov, self.placement_cov
        out[12:, 12:] = np.diag(self.surface_sigma_mm**2)
        return out


@dataclass(frozen=True)
class Anchor:
    """The zero's survey: `offset_mm` from the rig's arc lengths to the fixes', and the survey's
    sensitivity to the model's parameters (fixes are taken relative to it)."""

    offset_mm: float
    gradient: FloatArray | None  # None: the model taken as exact


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
    sigma_mm: float  # the reading's own (noise, head angles)
    surface: str
    systematic_mm: float = 0.0  # σ of the model's bias in s_mm (shared by neighbouring fixes)
    # ∂s_mm/∂(the model's parameters, `Systematic` order); None: the model taken as exact
    gradient: FloatArray | None = None

    @property
    def total_sigma_mm(self) -> float:
        """The reading's σ and the model's together, for a filter that cannot hold the bias."""
        return math.hypot(self.sigma_mm, self.systematic_mm)


@dataclass
class RangeFixer:
    """Inverts r(s) for readings of surveyed surfaces, near a predicted s."""

    rig: Rig
    scene: RangeScene
    config: RangeFixConfig = field(default_factory=RangeFixConfig)
    stats: RangeFixStats = field(default_factory=RangeFixStats)
    systematic: Systematic | None = None  # None: the model taken as exact
    anchor: Anchor | None = None  # the zero's survey; None: fixes in the model's arc lengths

    def anchor_at(
        self, zero_s_mm: float, pan_rad: float, tilt_rad: float, surveyed_mm: float
    ) -> None:
        """The rig's zero, at `zero_s_mm` in its arc lengths, was surveyed through this model
        from these head angles as `surveyed_mm`: take later fixes relative to that survey."""
        slope = self._slope(surveyed_mm, pan_rad, tilt_rad)
        gradient = (
            None if slope is None or self.systematic is None
            else self._gradient(surveyed_mm, pan_rad, tilt_rad, *slope)
        )  # fmt: skip
        self.anchor = Anchor(surveyed_mm - zero_s_mm, gradient)

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
        offset = self.anchor.offset_mm if self.anchor is not None else 0.0
        s_pred_mm += offset  # in the model's own arc lengths
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
        name = self.scene.surfaces[hit.surface].name
        st.fixes += 1
        if self.systematic is None:
            return RangeFix(s - offset, sigma_r / abs(drds), name)
        g = self._gradient(s, pan_rad, tilt_rad, hit, drds)
        if self.anchor is not None and self.anchor.gradient is not None:
            g = g - self.anchor.gradient
        return RangeFix(s - offset, sigma_r / abs(drds), name, self._sigma(g), g)

    def _sigma(self, g: FloatArray) -> float:
        """σ of a fix's error from the model's parameters, for its gradient g."""
        assert self.systematic is not None
        return math.sqrt(max(float(g @ self.systematic.covariance @ g), 0.0))

    def _gradient(self, s_mm: float, pan: float, tilt: float, hit: Hit, drds: float) -> FloatArray:
        """∂s_fix/∂(mount δ, placement δ, surface offsets), first order.

        r = n·(p − o)/(n·z) for beam origin o, direction z and the surface's point p, normal n;
        a local perturbation exp(δ) of a frame F moves a point x by R_F (ω × x_F + t) and a
        direction by R_F (ω × z_F). The fix moves by −∂r/(∂r/∂s).
        """
        T_w_l = self.rig.T_w_r(s_mm, pan, tilt) @ self.rig.T_r_l
        o, z, R_wl = T_w_l[:3, 3], T_w_l[:3, 2], T_w_l[:3, :3]
        surf = self.scene.surfaces[hit.surface]
        n = np.asarray(surf.normal_w, dtype=np.float64)
        nz, r = float(n @ z), hit.distance_mm

        def dr(do: FloatArray, dz: FloatArray) -> FloatArray:  # columns per parameter
            out: FloatArray = -(n @ do) / nz - r * (n @ dz) / nz
            return out

        e_z = np.array([0.0, 0.0, 1.0])
        mount = np.concatenate(
            [dr(np.zeros((3, 3)), -R_wl @ _skew(e_z)), dr(R_wl, np.zeros((3, 3)))]
        )
        T_wt = self.rig.track.T_w_track
        R_wt = T_wt[:3, :3]
        o_t, z_t = R_wt.T @ (o - T_wt[:3, 3]), R_wt.T @ z
        placement = np.concatenate(
            [dr(-R_wt @ _skew(o_t), -R_wt @ _skew(z_t)), dr(R_wt, np.zeros((3, 3)))]
        )
        surfaces = np.zeros(len(self.scene.surfaces))
        surfaces[hit.surface] = 1.0 / nz
        out: FloatArray = -np.concatenate([mount, placement, surfaces]) / drds
        return out

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


def _skew(v: FloatArray) -> FloatArray:
    """[v]×: the cross product with v as a matrix."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
