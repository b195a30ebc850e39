"""Map the controller's 32-bit microsecond clock to host monotonic nanoseconds.

A pure estimator fed numbers, no I/O (the idea follows Klipper's clocksync.py; the code is ours).
Each CLOCK_SYNC probe gives four timestamps, as in NTP: the host send time t0, the controller
time the probe arrived (rx), the controller time the reply was queued (tx), and the host receive
time t1. The controller held the probe for tx − rx (waiting for its tick); the rest of the round
trip, the *delay*, was spent on the link, and half of it is taken as the way out. The probes with
the shortest delay pin the controller clock best, so every probe is weighted by how far its delay
lies above the recent minimum. The fit is an exponentially decaying weighted linear regression of
host time on extended controller time, so a constant drift costs nothing and old probes fade
out. The fit is recomputed from the kept probes after each one, so a newly found lower minimum
delay re-weights the past instead of leaving early, slow probes trusted. Probes that disagree
with the prediction by far more than their delay can explain are rejected as outliers.

No estimator can see a difference between the two legs' *minimum* delays; it shifts the mapping
by half that difference. When a link's asymmetry is known, `outbound_fraction` corrects it.

The probes fix the offset well but their slope poorly on a busy half-duplex radio, where the
queues they meet bias each one's offset by an amount that changes with the traffic: over XBee the
probes' slope was 10-20 ppm off for a minute at a time. Telemetry frames give the slope without
a probe: `add_arrival` feeds each frame's newest MCU stamp and arrival time to the lower envelope
of one-way delays (`host.link.skew`), and the fit weighs its slope against the probes' by their
variances. Without telemetry the probes' slope stands alone, as before.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass

from host.link.skew import SkewEnvelope, SkewEstimate

WRAP_US = 1 << 32
HALF_WRAP_US = 1 << 31
NS_PER_S = 1_000_000_000

DECAY_TIME_S = 60.0  # time constant of the regression: long enough to average jitter out
HISTORY_PROBES = 900  # probes kept for the fit (90 s at 10 Hz)
QUANTILE_WINDOW = 128  # recent probes whose delay spread sets the cutoff (~13 s at 10 Hz)
BASE_SIGMA_NS = 20_000  # floor of a probe's timing error even at the minimum delay
KEEP_FASTEST_FRACTION = 0.15  # share of probes, by delay, that enter the fit
MIN_EXCESS_CUTOFF_NS = 100_000  # never cut tighter than this above the minimum delay
MIN_FIT_PROBES = 4  # below this the nominal rate is used for the slope
PRIOR_SPAN_US = 1_000_000  # the slope leans on the nominal rate as if probes spanned ~1 s
OUTLIER_SIGMAS = 6.0
OUTLIER_FLOOR_NS = 200_000
MAX_CONSECUTIVE_OUTLIERS = 8  # then assume a clock step and start over


@dataclass(frozen=True)
class ClockEstimate:
    """A snapshot of the fit, for statistics and logs."""

    ns_per_tick: float  # host ns per controller tick (1000 at a perfect 1 MHz clock)
    drift_ppm: float  # deviation of the controller clock from its nominal rate
    min_delay_ns: float | None  # shortest round trip on the link, controller residence excluded
    probes_used: int
    filtered: int  # probes left out for a slow round trip
    outliers: int
    inconsistent: int  # replies whose residence exceeded their round trip
    sigma_ns: float  # residual scatter of the weighted fit
    telemetry_frames: int = 0  # frames whose arrival fed the rate (add_arrival) in this fit


class ClockSync:
    """Estimator of host time from controller time, fed by CLOCK_SYNC probes."""

    _fit: _Fit | None

    def __init__(
        self,
        mcu_clock_hz: int = 1_000_000,
        outbound_fraction: float = 0.5,
        asymmetry_sigma_ns: float = 0.0,
    ) -> None:
        """`outbound_fraction`: share of the minimum delay spent on the way to the controller.
        `asymmetry_sigma_ns`: σ of the legs' uneven split that no round trip shows (a radio's
        queues), part of `uncertainty_ns`; it moves the mapping as a bias, not as scatter."""
        if mcu_clock_hz <= 0 or not 0.0 <= outbound_fraction <= 1.0 or asymmetry_sigma_ns < 0:
            raise ValueError(
                "mcu_clock_hz must be > 0, outbound_fraction in [0, 1], asymmetry_sigma_ns >= 0"
            )
        self.nominal_ns_per_tick = NS_PER_S / mcu_clock_hz
        self.outbound_fraction = outbound_fraction
        self.asymmetry_sigma_ns = asymmetry_sigma_ns
        self.probes_used = 0
        self.outliers = 0
        self.filtered = 0
        self.inconsistent = 0
        self.reset()

    def reset(self) -> None:
        """Forget everything (the controller rebooted: its clock restarted)."""
        self._last_ext: int | None = None
        self._restart_fit()

    @property
    def ready(self) -> bool:
        """True once at least one probe was accepted."""
        return self._fit is not None

    def extend(self, mcu_ticks_32: int) -> int:
        """Extend a 32-bit counter value to 64 bits, nearest to the latest one seen."""
        ext = self._extend_query(mcu_ticks_32)
        self._last_ext = ext if self._last_ext is None else max(self._last_ext, ext)
        return ext

    def _extend_query(self, mcu_ticks_32: int) -> int:
        """Like extend(), without moving the reference: for queries that must not change state."""
        if self._last_ext is None:
            return mcu_ticks_32 & (WRAP_US - 1)
        delta = (mcu_ticks_32 - self._last_ext) & (WRAP_US - 1)
        # Past half the wrap the stamp is slightly older than the newest: step back.
        return self._last_ext + (delta - WRAP_US if delta >= HALF_WRAP_US else delta)

    def add_probe(
        self, t0_ns: int, mcu_ticks_32: int, t1_ns: int, rx_ticks_32: int | None = None
    ) -> bool:
        """Feed one probe; True if it was used, False if rejected (slow, outlier, inconsistent).

        `t0_ns`, `t1_ns`: host send and receive times; `mcu_ticks_32`: controller clock as the
        reply was queued; `rx_ticks_32`: controller clock when the probe arrived (None, or equal
        to `mcu_ticks_32`, for a controller that cannot stamp arrivals: the plain midpoint).
        """
        rtt = t1_ns - t0_ns
        if rtt < 0:
            return False
        held = 0 if rx_ticks_32 is None else (mcu_ticks_32 - rx_ticks_32) & (WRAP_US - 1)
        residence = held * self.nominal_ns_per_tick
        if residence > rtt:
            # The controller cannot have held the probe longer than the round trip: a wrong
            # stamp (or, in a simulator, a tick that ran after its own time): nothing to learn.
            self.inconsistent += 1
            return False
        probe = _Probe(self.extend(mcu_ticks_32), t0_ns, rtt - residence, residence)
        self._history.append(probe)
        min_delay = min(p.delay for p in self._history)
        if probe.delay - min_delay > self._excess_cutoff(min_delay):
            self.filtered += 1
            return False
        if self._is_outlier(probe, min_delay):
            probe.outlier = True
            return False
        self._fit = self._solve(min_delay)
        self.probes_used += 1
        return True

    def add_arrival(self, kind: object, mcu_ticks_32: int, arrival_ns: int) -> None:
        """A telemetry frame arrived: `mcu_ticks_32` is its newest sample's stamp, `kind` tells
        apart frames whose least delay differs (message and length). Used from the next probe."""
        self._skew.add(kind, self.extend(mcu_ticks_32), arrival_ns)

    def skew(self) -> SkewEstimate | None:
        """The telemetry envelope's slope, for statistics; None until it has enough frames."""
        return self._skew.estimate()

    def mcu_to_host_ns(self, mcu_ticks_32: int) -> int:
        """Host monotonic ns at which the controller clock read `mcu_ticks_32`."""
        return self.ext_to_host_ns(self.extend(mcu_ticks_32))

    def peek_host_ns(self, mcu_ticks_32: int) -> int:
        """`mcu_to_host_ns` without moving the wrap extension's reference: for a query from
        outside the link (a score), which must leave the estimator as it was."""
        return self.ext_to_host_ns(self._extend_query(mcu_ticks_32))

    def ext_to_host_ns(self, mcu_ticks_64: int) -> int:
        """Host monotonic ns of an already extended controller time."""
        fit = self._require_fit()
        return fit.y0 + round(fit.my + fit.slope * (mcu_ticks_64 - fit.x0 - fit.mx))

    def host_to_mcu(self, host_ns: int) -> int:
        """Extended (64-bit) controller ticks at host time `host_ns`; mask with 2³²-1 for wire."""
        fit = self._require_fit()
        return fit.x0 + round(fit.mx + (host_ns - fit.y0 - fit.my) / fit.slope)

    def uncertainty_ns(self, mcu_ticks_32: int | None = None) -> float:
        """One-sigma error of the mapping at that controller time (default: the latest probe):
        the fit's own, and the link's asymmetry σ."""
        fit = self._require_fit()
        x = fit.x_last if mcu_ticks_32 is None else self._extend_query(mcu_ticks_32)
        dx = x - fit.x0 - fit.mx
        statistical = fit.unit_var / fit.w + fit.slope_var * dx * dx
        return math.sqrt(statistical + self.asymmetry_sigma_ns**2)

    def estimate(self) -> ClockEstimate:
        """Snapshot of the fit."""
        fit = self._fit
        slope = fit.slope if fit is not None else self.nominal_ns_per_tick
        return ClockEstimate(
            ns_per_tick=slope,
            drift_ppm=(self.nominal_ns_per_tick / slope - 1.0) * 1e6,
            min_delay_ns=min((p.delay for p in self._history), default=None),
            probes_used=self.probes_used,
            filtered=self.filtered,
            outliers=self.outliers,
            inconsistent=self.inconsistent,
            sigma_ns=math.sqrt(fit.rss / fit.w) if fit is not None else 0.0,
            telemetry_frames=self._skew.frames,
        )

    def _restart_fit(self) -> None:
        """Drop the probes and the envelope (both belong to the old clock), keep the wrap
        extension."""
        self._history: deque[_Probe] = deque(maxlen=HISTORY_PROBES)
        self._skew = SkewEnvelope(self.nominal_ns_per_tick)
        self._fit = None
        self._consecutive_outliers = 0
        self._streak_start_ns = 0

    def _require_fit(self) -> _Fit:
        """Mapping before the first probe is a caller error, reported clearly."""
        if self._fit is None:
            raise RuntimeError("clock sync has no probe yet")
        return self._fit

    def _excess_cutoff(self, min_delay: float) -> float:
        """Keep only the fastest probes: their timing error is at most half their excess."""
        recent = sorted(p.delay for p in itertools.islice(reversed(self._history), QUANTILE_WINDOW))
        quantile = recent[int(len(recent) * KEEP_FASTEST_FRACTION)]
        return max(quantile - min_delay, MIN_EXCESS_CUTOFF_NS)

    def _is_outlier(self, probe: _Probe, min_delay: float) -> bool:
        """A probe far off the prediction, beyond what its own delay can explain."""
        fit = self._fit
        if fit is None or fit.sxx <= 0.0:
            return False
        y, sigma2 = self._host_time(probe, min_delay)
        residual = y - self.ext_to_host_ns(probe.x)
        limit = max(OUTLIER_SIGMAS * math.sqrt(sigma2 * fit.unit_var), OUTLIER_FLOOR_NS)
        if abs(residual) <= limit:
            self._consecutive_outliers = 0
            return False
        self.outliers += 1
        self._consecutive_outliers += 1
        if self._consecutive_outliers == 1:
            self._streak_start_ns = probe.t0
        if self._consecutive_outliers >= MAX_CONSECUTIVE_OUTLIERS:
            # The clock jumped: the old probes are worthless, the outlier streak is the truth.
            recent = [p for p in self._history if p.t0 >= self._streak_start_ns]
            self._restart_fit()
            for p in recent:
                p.outlier = False
                self._history.append(p)
            return False
        return True

    def _host_time(self, probe: _Probe, min_delay: float) -> tuple[float, float]:
        """Host time at which the controller queued the reply, and the variance of that guess."""
        excess = probe.delay - min_delay
        # Beyond the minimum, the extra delay is equally likely on either leg: split it. The
        # probe reached the controller after its outbound leg and waited `residence` there.
        y = probe.t0 + self.outbound_fraction * min_delay + excess / 2 + probe.residence
        return y, BASE_SIGMA_NS**2 + (excess / 2) ** 2

    def _solve(self, min_delay: float) -> _Fit:
        """Decaying weighted least squares over the kept probes (centred, numerically stable)."""
        newest = max(p.x for p in self._history)
        cutoff = self._excess_cutoff(min_delay)
        acc = _Accumulator(newest, self._history[-1].t0)
        for p in self._history:
            if p.outlier or p.delay - min_delay > cutoff:
                continue
            y, sigma2 = self._host_time(p, min_delay)
            age_s = (newest - p.x) * self.nominal_ns_per_tick / NS_PER_S
            acc.add(p.x, y, math.exp(-age_s / DECAY_TIME_S) / sigma2)
        return acc.result(self.nominal_ns_per_tick, self._skew.estimate())


@dataclass
class _Probe:
    """One probe as kept for the fit."""

    x: int  # extended controller ticks when the reply was queued
    t0: int  # host send time, ns
    delay: float  # round trip minus the controller's residence, ns
    residence: float  # how long the controller held the probe, ns
    outlier: bool = False


@dataclass(frozen=True)
class _Fit:
    """Result of the regression: y = y0 + my + slope·(x − x0 − mx)."""

    x0: int
    y0: int
    mx: float
    my: float
    slope: float
    sxx: float  # the probes' spread in x, weighted (0 while the slope is not fitted)
    w: float
    rss: float
    unit_var: float
    x_last: int
    slope_var: float  # variance of the slope, probes and envelope together


class _Accumulator:
    """West's weighted incremental mean and co-moments, relative to an origin."""

    def __init__(self, x0: int, y0: int) -> None:
        self.x0, self.y0 = x0, y0
        self.w = self.w2 = self.mx = self.my = self.sxx = self.sxy = self.syy = 0.0
        self.n = 0

    def add(self, x: int, y: float, weight: float) -> None:
        """Add one weighted point."""
        rx, ry = float(x - self.x0), y - self.y0
        self.w += weight
        self.w2 += weight * weight
        dx, dy = rx - self.mx, ry - self.my
        self.mx += weight / self.w * dx
        self.my += weight / self.w * dy
        self.sxx += weight * dx * (rx - self.mx)
        self.sxy += weight * dx * (ry - self.my)
        self.syy += weight * dy * (ry - self.my)
        self.n += 1

    def result(self, nominal_slope: float, skew: SkewEstimate | None) -> _Fit:
        """The fit. Its slope leans on the nominal rate as if the probes spanned another
        PRIOR_SPAN_US, so that a short history cannot pull it far off, and on the envelope's
        slope by its variance. Too few probes: the envelope's or the nominal slope alone."""
        if self.n < MIN_FIT_PROBES:
            slope = nominal_slope if skew is None else skew.ns_per_tick
            rss, unit_var = self._residuals(slope)
            slope_var = 0.0 if skew is None else skew.variance
            return self._fit(slope, 0.0, rss, unit_var, slope_var)
        ridge = self.w * PRIOR_SPAN_US**2
        _, unit_var = self._residuals((self.sxy + ridge * nominal_slope) / (self.sxx + ridge))
        # In the regression's units a slope known to variance v weighs as unit_var / v. The
        # nominal rate is no measurement (a crystal can be tens of ppm off): it steadies the
        # slope but is not counted in its variance.
        envelope = 0.0 if skew is None else unit_var / skew.variance
        prior_sum = ridge * nominal_slope + (0.0 if skew is None else envelope * skew.ns_per_tick)
        slope = (self.sxy + prior_sum) / (self.sxx + ridge + envelope)
        rss, _ = self._residuals(slope)
        slope_var = unit_var / (self.sxx + envelope) if self.sxx + envelope > 0.0 else 0.0
        return self._fit(slope, self.sxx, rss, unit_var, slope_var)

    def _residuals(self, slope: float) -> tuple[float, float]:
        """Weighted residual sum of squares about that slope, and the unit variance."""
        rss = max(self.syy - 2 * slope * self.sxy + slope * slope * self.sxx, 0.0)
        n_eff = self.w**2 / self.w2
        return rss, max(rss / max(n_eff - 2.0, 1.0), 1.0)

    def _fit(self, slope: float, sxx: float, rss: float, unit_var: float, slope_var: float) -> _Fit:
        """The snapshot, through the weighted means."""
        return _Fit(
            self.x0,
            self.y0,
            self.mx,
            self.my,
            slope,
            sxx,
            self.w,
            rss,
            unit_var,
            self.x0,
            slope_var,
        )
