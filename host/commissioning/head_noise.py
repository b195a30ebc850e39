"""The head's angle read noise, measured: the scatter of its reported angles while it stands.

The error budget needs how far a head reading is from the angle the head truly stands at. A
datasheet gives a bound (resolution and noise in quadrature), but a head whose servos close on
the same encoder it reads stands on a count and reads that count, except when the noise crosses
half a count: at rest it reads far better than the bound. Commissioning measures it: at every
rest of a board run (the head still, waiting for a frame) the readings' scatter about their
mean, pooled over the rests and both axes, as the pose lookups take them: each the median of
it and its two neighbours (`AngleBuffer`), so a lone count of flicker, which no frame sees, does
not count (the raw scatter goes into the note; a moving head's readings pass that median as
read, so in motion the raw one applies). Readings that never moved prove only that the
noise seldom crosses a count: one step is then counted (the smallest seen, or the datasheet's
resolution when none moved), so a quiet head is never written as exact.

A commissioning view takes its angles as the median of all its rest's readings, which reads
better still: `rest_sigma` scales the looked-up σ to that many readings (the hand-eye fit's
share of the head). Passing the looked-up σ there instead counted the head's error about three
times over on a ten-reading rest, and the fit's M_cr and intrinsics came out with a σ the
seeded rigs did not reach (bench_budget's NEES 13 of 19).

What this does not see is an error that stays put while the head stands (a servo resting
between counts): the hand-eye residual and `calibrate check` judge those.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from host.geometry.transforms import FloatArray, angle_median
from host.rig import Provenance, Scalar
from host.rig.schema import HEAD_RESOLUTION_RAD

MIN_READINGS = 40  # over all rests and both axes, or the datasheet's value is kept
REPORTED_RESOLUTION_RAD = 1e-5  # the snapshot's head angles (5 digits): smaller is no step
METHOD = "measured at rest (scatter of the head's readings)"


@dataclass(frozen=True)
class ReadNoise:
    """The head's read noise at rest, pooled over both axes."""

    sigma_rad: float  # as the pose lookups take the readings (the median of three)
    raw_sigma_rad: float  # as read
    readings: int


def read_noise(rests: Sequence[FloatArray]) -> ReadNoise | None:
    """Pooled over the rests ((n, 2) pan/tilt each), or None with too few readings."""
    looked_up, raw = _Pool(), _Pool()
    readings = 0
    steps: list[float] = []
    for r in rests:
        a = np.asarray(r, dtype=np.float64).reshape(-1, 2)
        a = np.unwrap(a[np.isfinite(a).all(axis=1)], axis=0)  # a pan stop at ±π
        if len(a) < 3:
            continue
        looked_up.add(np.array([angle_median(a[i - 1 : i + 2]) for i in range(1, len(a) - 1)]))
        raw.add(a)
        readings += 2 * len(a)
        moved = np.abs(np.diff(a, axis=0))
        steps += [float(x) for x in moved[moved > 0.5 * REPORTED_RESOLUTION_RAD]]
    if readings < MIN_READINGS or looked_up.dof == 0:
        return None
    # one step over all the readings: the median drops lone steps, not the readings they were in
    floor_sq = (min(steps) if steps else HEAD_RESOLUTION_RAD) ** 2 / raw.dof
    return ReadNoise(looked_up.sigma(floor_sq), raw.sigma(floor_sq), readings)


def rest_sigma(looked_up_sigma_rad: float, readings: int) -> float:
    """σ of a rest's angles taken as the median of its `readings` readings, from the σ of one
    as the lookups take it (the median of three): a median's variance falls as 1/n, so
    σ·√(3/n); with fewer than three readings the looked-up σ stands."""
    return looked_up_sigma_rad * math.sqrt(3.0 / max(readings, 3))


@dataclass
class _Pool:
    """Squared deviations of each rest's readings about their mean, and their dof."""

    sq: float = 0.0
    dof: int = 0

    def add(self, a: FloatArray) -> None:
        dev = a - a.mean(axis=0)
        self.sq += float(np.sum(dev * dev))
        self.dof += dev.size - a.shape[1]

    def sigma(self, floor_sq: float) -> float:
        """σ, its square at least `floor_sq` (a quiet head is never exact)."""
        return math.sqrt(max(self.sq / self.dof, floor_sq))


def angle_noise_update(rests: Sequence[FloatArray], views: int) -> dict[str, Scalar]:
    """`head.angle_noise` as measured over the rests ({} with too few readings)."""
    got = read_noise(rests)
    if got is None:
        return {}
    sigma, n = got.sigma_rad, got.readings
    note = (
        f"{n} readings over {views} rests, {got.raw_sigma_rad:.2g} rad as read; a head resting "
        "between counts is not seen"
    )
    prov = Provenance.now(METHOD, sigma, "rad", views, note)
    return {"head.angle_noise": Scalar(0.0, sigma, prov)}
