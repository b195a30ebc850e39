"""Drift correction beyond the paper: fuse sprocket odometry with absolute track references.

The encoder sits on the sprocket, so it cannot see chain elongation (a scale error that grows
with travel) or a tooth skip (a jump of one chain pitch). Absolute references do: the home
switch, marks along the track, a rangefinder reading of a known feature. This filter estimates

    s_true = offset + scale · s_encoder

as a two-state Kalman filter over (offset, scale) with process noise per millimetre travelled.
A reference whose innovation is far outside its gate but within a few millimetres of a whole
number k of chain pitches is taken as a tooth skip: the trolley jumped k true pitches
(k · pitch · scale), so the offset is moved by exactly that — its uncertainty through the
scale's — and the reference is then applied as usual. The scale is untouched by the jump, and
a single stray reading that happens to mimic a skip is undone by the next good one, which then
looks like the opposite skip. A skip is decided only when the evidence tells one pitch from the
next: one sharp reference (a mark) suffices; coarse ones (a rangefinder reading at a shallow
angle) are pooled while consecutive ones agree on the same whole number of pitches, until
their combined σ is small enough. Other gross outliers are rejected and counted.

A reference may also rest on a model the rig file knows only to its σ: a rangefinder fix is
solved through the mount, the track's placement and the walls' survey, whose errors bias every
fix from the same geometry alike. Those parameters (`ChainFilterConfig.bias_cov`, their prior
covariance) are then states of the filter beside (offset, scale): such a reference passes its
sensitivity to them (`gradient`) and is weighed with the correlation it really has with its
neighbours, instead of as independent noise. A bias shared along a straight is learnt as one
combination and leaves the sharp relative information (stretch, skips) intact; where the
geometry changes (a corner, another wall) the fixes tell the parameters apart as far as they
can, and never pull the position by more than the stated σ allows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

GATE_SIGMAS = 4.0  # innovations beyond this many σ are not taken at face value
HOMING_REPEATABILITY_MM = 1.0  # σ of the zero between homings: the same switch and index
SKIP_TOLERANCE_MM = 2.0  # how near a whole number of pitches a jump must be to be a skip
# A reference may call a skip only if its σ (with the prediction's) keeps the tolerance band,
# widened by GATE_SIGMAS σ, inside half a pitch: otherwise k and k ± 1 pitches both fit.


@dataclass(frozen=True)
class ChainFilterConfig:
    """Noise model and references; lengths in mm."""

    chain_pitch_mm: float = 12.7
    scale_sigma0: float = 0.01  # prior σ of the chain scale (1 %: worn chains stretch ≲ 3 %)
    # prior σ of the offset after homing: the homing's repeatability, and how well the zero's
    # place on the track is known (a rig file's home σ: `rig_references.chain_config`)
    offset_sigma0_mm: float = HOMING_REPEATABILITY_MM
    scale_walk_per_m: float = 1e-5  # scale random walk, σ per √m of travel
    offset_walk_mm_per_m: float = 0.02  # offset random walk, mm per √m of travel
    reference_sigma_mm: float = 0.1  # σ of one reference detection
    association_gate_mm: float = 300.0  # farthest a reference may be from the prediction
    max_skip_teeth: int = 3
    # prior covariance of the parameters references may be biased by (None: none are)
    bias_cov: FloatArray | None = field(default=None, compare=False)


@dataclass
class FilterStats:
    """What the filter has done, for the report and the link statistics."""

    updates: int = 0
    skips_detected: int = 0
    rejected: int = 0
    unassociated: int = 0


@dataclass
class ChainFilter:
    """Kalman filter over (offset, scale) mapping encoder arc length to true arc length, and the
    references' bias parameters when the configuration has them (states 2 on)."""

    config: ChainFilterConfig = field(default_factory=ChainFilterConfig)
    x: FloatArray = field(default_factory=lambda: np.array([0.0, 1.0]))
    p: FloatArray = field(default_factory=lambda: np.zeros((2, 2)))
    stats: FilterStats = field(default_factory=FilterStats)
    _last_enc_mm: float | None = None
    # Consecutive gated-out references that agree on a skip: (teeth, Σ 1/r, Σ innovation/r).
    _pending: tuple[int, float, float] | None = None

    def __post_init__(self) -> None:
        c = self.config
        bias = np.zeros((0, 0)) if c.bias_cov is None else np.asarray(c.bias_cov, np.float64)
        n = 2 + len(bias)
        self.x = np.concatenate([self.x[:2], np.zeros(len(bias))])
        self.p = np.zeros((n, n))
        self.p[:2, :2] = np.diag([c.offset_sigma0_mm**2, c.scale_sigma0**2])
        self.p[2:, 2:] = bias

    @property
    def pooling(self) -> bool:
        """Whether the last gated-out references are being pooled as the evidence of a skip."""
        return self._pending is not None

    @property
    def biases(self) -> int:
        """How many bias parameters the filter carries."""
        return len(self.x) - 2

    def predict(self, enc_mm: float) -> None:
        """Grow the uncertainty with the travel since the last call."""
        if self._last_enc_mm is not None:
            travel_m = abs(enc_mm - self._last_enc_mm) / 1000.0
            c = self.config
            self.p[0, 0] += c.offset_walk_mm_per_m**2 * travel_m
            self.p[1, 1] += c.scale_walk_per_m**2 * travel_m
        self._last_enc_mm = enc_mm

    def estimate(self, enc_mm: float) -> tuple[float, float]:
        """True arc length for an encoder reading, and its σ in mm."""
        h = np.array([1.0, enc_mm])
        return float(h @ self.x[:2]), math.sqrt(max(float(h @ self.p[:2, :2] @ h), 0.0))

    def correct(self, enc_mm: FloatArray) -> FloatArray:
        """True arc lengths for many encoder readings at once (the current estimate)."""
        out: FloatArray = self.x[0] + self.x[1] * np.asarray(enc_mm, dtype=np.float64)
        return out

    def reference(
        self,
        enc_mm: float,
        true_mm: float,
        sigma_mm: float | None = None,
        advance: bool = True,
        gradient: FloatArray | None = None,
    ) -> bool:
        """Apply one absolute reference (the encoder read enc_mm at true position true_mm).

        `advance=False` for a reference older than the newest encoder reading: its travel has
        already been counted by `predict`, and counting it back and forth would inflate it.
        `gradient`: the reference's sensitivity to the bias parameters (true_mm reads the true
        position plus gradient · bias); None for a reference that rests on none of them.
        `sigma_mm` is then the reference's own noise only.
        """
        if advance:
            self.predict(enc_mm)
        r = (sigma_mm if sigma_mm is not None else self.config.reference_sigma_mm) ** 2
        h = np.zeros(len(self.x))
        h[:2] = 1.0, enc_mm
        if gradient is not None and self.biases:
            h[2:] = gradient
        innovation = true_mm - float(h @ self.x)
        s = float(h @ self.p @ h) + r
        if innovation**2 > GATE_SIGMAS**2 * s:
            if not self._apply_skip(innovation, float(h @ self.p @ h), r):
                self.stats.rejected += 1
                return False
            innovation = true_mm - float(h @ self.x)
            s = float(h @ self.p @ h) + r
        self._pending = None
        gain = self.p @ h / s
        self.x = self.x + gain * innovation
        self.p = self.p - np.outer(gain, h @ self.p)
        self.p = 0.5 * (self.p + self.p.T)
        self.stats.updates += 1
        return True

    def associate(self, enc_mm: float, marks_mm: tuple[float, ...]) -> float | None:
        """The reference mark nearest the predicted position, if inside the gate."""
        if not marks_mm:
            return None
        predicted, _ = self.estimate(enc_mm)
        nearest = min(marks_mm, key=lambda m: abs(m - predicted))
        if abs(nearest - predicted) > self.config.association_gate_mm:
            self.stats.unassociated += 1
            return None
        return nearest

    def _apply_skip(self, innovation: float, predicted_var: float, r: float) -> bool:
        """If the evidence says whole tooth skips, move the offset by them; else leave all as is.

        The evidence is this reference pooled with the consecutive ones before it that pointed
        at the same number of teeth; the prediction's variance is common to all of them.
        """
        c = self.config
        true_pitch = c.chain_pitch_mm * float(self.x[1])
        teeth = round(innovation / true_pitch)
        if teeth == 0 or abs(teeth) > c.max_skip_teeth:
            self._pending = None
            return False
        weight, weighted = 1.0 / r, innovation / r
        if self._pending is not None and self._pending[0] == teeth:
            weight += self._pending[1]
            weighted += self._pending[2]
        self._pending = (teeth, weight, weighted)
        pooled = weighted / weight
        band = SKIP_TOLERANCE_MM + GATE_SIGMAS * math.sqrt(predicted_var + 1.0 / weight)
        if band >= 0.5 * true_pitch or abs(pooled - teeth * true_pitch) > band:
            return False
        # offset' = offset + teeth · pitch · scale: shift it, carry the scale's σ into it.
        jump = np.eye(len(self.x))
        jump[0, 1] = teeth * c.chain_pitch_mm
        self.x = self.x.copy()
        self.x[0] += teeth * true_pitch
        self.p = jump @ self.p @ jump.T
        self._pending = None
        self.stats.skips_detected += 1
        return True
