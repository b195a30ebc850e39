"""Time-indexed sample buffers and the camera pose at a frame's exposure time.

Samples are stamped in host monotonic nanoseconds. A lookup interpolates between the two samples
around the query time; past the newest sample it extrapolates at most `horizon_ns`, and before
the oldest retained sample it refuses. A sample pushed with `after_reset` starts a new segment
(the encoder's zero was reset between it and the one before): no lookup bridges two segments,
since a value between them is a position the trolley never had. Results say ok / stale / empty
and never carry a guess.

Joint samples (track s, head pan/tilt) are interpolated linearly in joint space, which is exact
for the kinematic chain; `TransformBuffer` holds whole poses and interpolates them as ROS tf2
does (slerp on rotation, linear on translation), for pose streams without joint values.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import numpy.typing as npt

from host.geometry.head import Rig
from host.geometry.track import Track
from host.geometry.transforms import (
    FloatArray,
    R_from_quat,
    angle_median,
    make_T,
    quat_from_R,
    slerp,
)

Int64Array = npt.NDArray[np.int64]

DEFAULT_CAPACITY = 4096  # samples kept per buffer (≈ 4 s of a 1 kHz encoder stream)
DEFAULT_HORIZON_NS = 20_000_000  # extrapolate at most 20 ms past the newest sample
DEFAULT_MAX_GAP_NS = 100_000_000  # refuse to bridge a hole in the stream longer than 100 ms


class LookupStatus(Enum):
    """Outcome of a buffer lookup."""

    OK = "ok"
    STALE = "stale"  # before the oldest sample, past the horizon, across a gap or a reset
    EMPTY = "empty"
    OFF_TRACK = "off_track"  # the trolley is outside the surveyed open track: no geometry there


@dataclass(frozen=True)
class Lookup:
    """Interpolated value at `t_ns`, or the reason there is none (`value` is then None)."""

    status: LookupStatus
    t_ns: int
    value: FloatArray | None = None
    extrapolated_ns: int = 0  # how far past the newest sample the value was carried

    @property
    def ok(self) -> bool:
        """True when a value is present."""
        return self.status is LookupStatus.OK


class SampleBuffer:
    """Ring buffer of (host time ns, k float channels) with linear interpolation."""

    def __init__(
        self,
        channels: int,
        capacity: int = DEFAULT_CAPACITY,
        horizon_ns: int = DEFAULT_HORIZON_NS,
        max_gap_ns: int = DEFAULT_MAX_GAP_NS,
    ) -> None:
        if capacity < 2 or channels < 1 or horizon_ns < 0 or max_gap_ns <= 0:
            raise ValueError("need capacity ≥ 2, channels ≥ 1, horizon ≥ 0, max_gap > 0")
        self.capacity, self.horizon_ns, self.max_gap_ns = capacity, horizon_ns, max_gap_ns
        # Every sample is written twice (at i and i + capacity) so the retained window is always
        # one contiguous slice, which keeps lookups a single searchsorted without copying.
        self._t: Int64Array = np.zeros(2 * capacity, dtype=np.int64)
        self._v: FloatArray = np.zeros((2 * capacity, channels))
        self._start = 0
        self._count = 0
        self.rejected = 0  # samples dropped for going back in time
        self._resets: deque[int] = deque()  # times of retained samples that start a segment
        # The link pushes on the event loop while the frame loop looks up in a worker thread: a
        # lookup must never see a half-advanced ring (times out of order, a wrong bracket).
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self._count

    def push(self, t_ns: int, values: npt.ArrayLike, after_reset: bool = False) -> bool:
        """Append a sample; returns False (and counts it) if it is not newer than the last.

        `after_reset`: the values' zero changed since the previous sample (a homing latched the
        encoder), so nothing is interpolated or extrapolated between the two.
        """
        with self._lock:
            return self._push(t_ns, values, after_reset)

    def _push(self, t_ns: int, values: npt.ArrayLike, after_reset: bool) -> bool:
        """push() under the lock."""
        if self._count and t_ns <= self._t[self._start + self._count - 1]:
            self.rejected += 1
            return False
        if after_reset and self._count:
            self._resets.append(t_ns)
        i = (self._start + self._count) % self.capacity
        self._t[i] = self._t[i + self.capacity] = t_ns
        self._v[i] = self._v[i + self.capacity] = values
        if self._count < self.capacity:
            self._count += 1
        else:
            self._start = (self._start + 1) % self.capacity
        oldest = self._t[self._start]
        while self._resets and self._resets[0] <= oldest:  # nothing retained before it to split
            self._resets.popleft()
        return True

    def newest_ns(self) -> int | None:
        """Stamp of the newest sample, None when empty."""
        with self._lock:
            return int(self._t[self._start + self._count - 1]) if self._count else None

    def clear(self) -> None:
        """Forget all samples (e.g. after a re-home or a clock resync)."""
        with self._lock:
            self._start = self._count = 0
            self._resets.clear()

    def revise(self, t_from_ns: int, values_at: Callable[[Int64Array], npt.ArrayLike]) -> int:
        """Rewrite the samples stamped at or after t_from_ns with values_at(their times).

        For a late correction (a drift fix that holds from a past instant on): frames looked
        up afterwards see it. Returns how many samples were rewritten.
        """
        with self._lock:
            t, _ = self._view()
            first = int(np.searchsorted(t, t_from_ns, side="left"))
            if first == len(t):
                return 0
            new = np.asarray(values_at(t[first:].copy()), dtype=np.float64)
            new = new.reshape(len(t) - first, -1)
            for k, row in enumerate(new):
                i = (self._start + first + k) % self.capacity
                self._v[i] = self._v[i + self.capacity] = row
            return len(new)

    def window(self) -> tuple[Int64Array, FloatArray]:
        """Copies of the retained times and values, oldest first."""
        with self._lock:
            t, v = self._view()
            return t.copy(), v.copy()

    def lookup(self, t_ns: int) -> Lookup:
        """Value at t_ns by interpolation, or bounded extrapolation past the newest sample."""
        with self._lock:
            return self._lookup(t_ns)

    def _view(self) -> tuple[Int64Array, FloatArray]:
        """Views of the retained window (valid only under the lock)."""
        sl = slice(self._start, self._start + self._count)
        return self._t[sl], self._v[sl]

    def _lookup(self, t_ns: int) -> Lookup:
        """lookup() under the lock."""
        if not self._count:
            return Lookup(LookupStatus.EMPTY, t_ns)
        t, v = self._view()
        if t_ns < t[0]:
            return Lookup(LookupStatus.STALE, t_ns)
        i = int(np.searchsorted(t, t_ns, side="right"))
        if i == len(t):
            return self._extrapolate(t, v, t_ns)
        t0, t1 = int(t[i - 1]), int(t[i])
        if t1 - t0 > self.max_gap_ns or t1 in self._resets:
            return Lookup(LookupStatus.STALE, t_ns)
        a, b = self._sample(t, v, i - 1), self._sample(t, v, i)
        return Lookup(LookupStatus.OK, t_ns, self._blend(a, b, (t_ns - t0) / (t1 - t0)))

    def _sample(self, t: Int64Array, v: FloatArray, j: int) -> FloatArray:
        """The value the lookup takes for retained sample j: the sample itself."""
        out: FloatArray = v[j]
        return out

    def _joined(self, t: Int64Array, j: int) -> bool:
        """Whether samples j and j + 1 lie in one segment with no gap between them."""
        return int(t[j + 1] - t[j]) <= self.max_gap_ns and int(t[j + 1]) not in self._resets

    def _extrapolate(self, t: Int64Array, v: FloatArray, t_ns: int) -> Lookup:
        """Carry the newest sample forward along the last velocity, within the horizon."""
        ahead = t_ns - int(t[-1])
        if ahead > self.horizon_ns:
            return Lookup(LookupStatus.STALE, t_ns, extrapolated_ns=ahead)
        # One sample of its segment, or after a gap: no velocity to carry it along.
        alone = len(t) < 2 or int(t[-1]) in self._resets
        last = np.array(self._sample(t, v, len(t) - 1))
        if ahead == 0 or alone or int(t[-1] - t[-2]) > self.max_gap_ns:
            return Lookup(LookupStatus.OK, t_ns, last, ahead)
        f = 1.0 + ahead / int(t[-1] - t[-2])
        return Lookup(
            LookupStatus.OK, t_ns, self._blend(self._sample(t, v, len(t) - 2), last, f), ahead
        )

    def _blend(self, a: FloatArray, b: FloatArray, f: float) -> FloatArray:
        """Linear interpolation of channel values at fraction f (f > 1 extrapolates)."""
        out: FloatArray = a + f * (b - a)
        return out


class AngleBuffer(SampleBuffer):
    """Angles in radians: interpolates along the shorter way round (no jump at ±π).

    An angle encoder standing still flickers between two counts: at the simulated head's
    1e-4 rad count and 2e-5 rad noise about one reading in forty is a count off, 0.3 mm at 3 m,
    and a frame that met it showed the overlay jump. So each sample the lookup takes is the
    median of it and its two neighbours in its segment: that drops a lone flicker and leaves a
    monotonic motion's samples as they were (no lag). The newest sample has no right neighbour
    yet: a step of at most `HOLD_RAD` from the one before is held back until the next sample
    confirms it (the median of the last three), a larger one is taken as read; the most a held
    step can be off is that step.
    """

    HOLD_RAD = 3e-4  # a few counts of a head's angle encoder; a slew steps far more a sample

    def _sample(self, t: Int64Array, v: FloatArray, j: int) -> FloatArray:
        if j >= 2 and j + 1 == len(t) and self._joined(t, j - 2) and self._joined(t, j - 1):
            lo, hi = j - 2, j + 1  # the newest: the last three
        elif 0 < j < len(t) - 1 and self._joined(t, j - 1) and self._joined(t, j):
            lo, hi = j - 1, j + 2
        else:
            return super()._sample(t, v, j)
        median = angle_median(v[lo:hi])
        if hi == j + 1:  # the newest: only its small steps wait
            step = np.abs(_turn(v[j - 1], v[j]))
            out: FloatArray = np.where(step <= self.HOLD_RAD, median, v[j])
            return out
        return median

    def _blend(self, a: FloatArray, b: FloatArray, f: float) -> FloatArray:
        out: FloatArray = a + f * _turn(a, b)
        return out


def _turn(a: FloatArray, b: FloatArray) -> FloatArray:
    """From angles a to b the shorter way round (rad, each in [-π, π))."""
    out: FloatArray = np.remainder(b - a + math.pi, 2.0 * math.pi) - math.pi
    return out


class TransformBuffer(SampleBuffer):
    """Whole poses T (4x4): slerp on rotation, linear on translation (as tf2)."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY, **kw: int) -> None:
        super().__init__(7, capacity, **kw)

    def push_T(self, t_ns: int, T: npt.ArrayLike) -> bool:
        """Append a pose, stored as quaternion (w, x, y, z) and translation."""
        T_ = np.asarray(T, dtype=np.float64)
        return self.push(t_ns, np.concatenate([quat_from_R(T_[:3, :3]), T_[:3, 3]]))

    def lookup_T(self, t_ns: int) -> Lookup:
        """Like lookup, with the value as a 4x4 pose."""
        r = self.lookup(t_ns)
        if r.value is None:
            return r
        T = make_T(R_from_quat(r.value[:4]), r.value[4:])
        return Lookup(r.status, r.t_ns, T, r.extrapolated_ns)

    def _blend(self, a: FloatArray, b: FloatArray, f: float) -> FloatArray:
        q = slerp(a[:4], b[:4], f) if 0.0 <= f <= 1.0 else _quat_extrapolate(a[:4], b[:4], f)
        return np.concatenate([q, a[4:] + f * (b[4:] - a[4:])])


def _quat_extrapolate(a: FloatArray, b: FloatArray, f: float) -> FloatArray:
    """Continue the rotation from a to b by the fraction f beyond [0, 1]."""
    Ra, Rb = R_from_quat(a), R_from_quat(b)
    qd = quat_from_R(Rb @ Ra.T)
    qd = qd if qd[0] >= 0.0 else -qd
    half = math.atan2(float(np.linalg.norm(qd[1:])), float(qd[0]))
    axis = qd[1:] / max(float(np.linalg.norm(qd[1:])), 1e-300)
    step = np.concatenate([[math.cos(f * half)], math.sin(f * half) * axis])
    return quat_from_R(R_from_quat(step) @ Ra)


@dataclass(frozen=True)
class PoseLookup:
    """Camera pose at a frame: T_w_c plus the joint values it came from, or why not."""

    status: LookupStatus
    t_exposure_ns: int
    T_w_c: FloatArray | None = None
    s_mm: float = math.nan
    pan_rad: float = math.nan
    tilt_rad: float = math.nan

    @property
    def ok(self) -> bool:
        """True when a pose is present."""
        return self.status is LookupStatus.OK


@dataclass
class PoseSource:
    """Camera pose at frame times from encoder and head buffers through the rig.

    A head without a sensor (the paper's manual turntable) uses the fixed angles instead.
    Encoder samples hold unwrapped arc length (a running count), so interpolation never
    crosses the loop seam; the track wraps s when it builds the pose.
    """

    rig: Rig
    encoder: SampleBuffer = field(default_factory=lambda: SampleBuffer(1))
    head: AngleBuffer | None = None
    fixed_pan_rad: float = 0.0
    fixed_tilt_rad: float = 0.0
    exposure_latency_ns: int = 0  # calibrated: frame timestamp minus mid-exposure time

    def pose_at(self, frame_t_ns: int) -> PoseLookup:
        """T_w_c at the exposure time of a frame stamped frame_t_ns."""
        t = frame_t_ns - self.exposure_latency_ns
        s = self.encoder.lookup(t)
        if s.value is None:
            return PoseLookup(s.status, t)
        pan, tilt = self.fixed_pan_rad, self.fixed_tilt_rad
        if self.head is not None:
            h = self.head.lookup(t)
            if h.value is None:
                return PoseLookup(h.status, t)
            pan, tilt = float(h.value[0]), float(h.value[1])
        s_mm = float(s.value[0])
        if not on_track(self.rig.track, s_mm):
            return PoseLookup(LookupStatus.OFF_TRACK, t, None, s_mm, pan, tilt)
        return PoseLookup(LookupStatus.OK, t, self.rig.T_w_c(s_mm, pan, tilt), s_mm, pan, tilt)


def on_track(track: Track, s_mm: float) -> bool:
    """Whether arc length s lies on the track: anywhere on a loop, within [0, L] on an open one."""
    if not math.isfinite(s_mm):
        return False
    return track.closed or 0.0 <= s_mm <= track.length_mm
