"""The controller clock's rate from the telemetry's one-way delays.

A pure estimator fed numbers, no I/O, used by `host.link.clocksync`. Each telemetry frame
carries the MCU time of its newest sample and reaches the host at a known time. Their
difference, less the nominal rate, is the frame's one-way delay plus the clocks' offset, and it
grows at the rate the controller's clock is off its nominal rate. Queues only ever add delay, so
the least delay seen in each second lies near a line whose slope is that rate error, however
loaded the link: the lower envelope, as in skew estimation from one-way delays (Moon, Skelly
and Towsley's idea; the fit here is ours). A clock probe's round trip meets the same queues and,
on a half-duplex radio, not evenly on both legs, so its offset is biased by an amount that
changes as the traffic does; over a minute that moves the probes' slope by tens of ppm, where
the envelope, ~50 frames a second, needs no probe at all.

Frames of each kind and length have a floor of their own (a longer frame spends longer on the
air and the UART), so each kind keeps its own minima. A robust line comes first (the median
slope between minima half the window apart), so that minima far off it (a second whose every
frame waited, a host stall) can be dropped; then one slope is fitted through the rest by least
squares, each kind with its own intercept and weighted by its own scatter.
The fit reports the slope's variance, so the clock sync can weigh it against its probes'.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

BIN_S = 1.0  # one minimum per kind per second of controller time
HISTORY_BINS = 120  # two minutes of minima per kind
MIN_BINS = 8  # a kind contributes once it has this many closed seconds
MAX_KINDS = 16  # kinds kept at once: the stalest is forgotten beyond this
FLOOR_SIGMA_NS = 50_000.0  # no kind's scatter is taken as tighter than this
# Successive minima are not independent (the floor wanders with the traffic): over the
# emulated XBee the slope's error was up to twice the independent figure, so its variance is
# taken four times that.
VARIANCE_INFLATION = 4.0
REJECT_SIGMAS = 4.0
MAD_TO_SIGMA = 1.4826  # a normal distribution's σ per median absolute deviation


@dataclass(frozen=True)
class SkewEstimate:
    """The envelope's slope in host ns per controller tick, and its variance."""

    ns_per_tick: float
    variance: float
    bins: int  # minima in the fit, all kinds
    rejected: int  # minima left out as far off the line


@dataclass
class _Kind:
    """The closed one-second minima of one kind of frame, and the second being filled."""

    bins: deque[tuple[float, float]]  # (x, d) relative to the envelope's origin
    open_bin: int
    open_x: float
    open_d: float
    last_seen: int
    opened: bool = False  # False while the open second is the kind's first


class SkewEnvelope:
    """Lower envelope of one-way delays, per kind of frame; one common slope."""

    def __init__(self, nominal_ns_per_tick: float) -> None:
        self.nominal = nominal_ns_per_tick
        self.bin_ticks = max(1, round(BIN_S * 1e9 / nominal_ns_per_tick))
        self._kinds: dict[object, _Kind] = {}
        self._origin: tuple[int, int] | None = None  # (ticks, ns) that d is measured from
        self._frames = 0
        self._cached: tuple[int, SkewEstimate | None] = (-1, None)

    def add(self, kind: object, mcu_ticks: int, arrival_ns: int) -> None:
        """One frame: `kind` tells frames with different floors apart, `mcu_ticks` is extended."""
        if self._origin is None:
            self._origin = (mcu_ticks, arrival_ns)
        x0, y0 = self._origin
        x = float(mcu_ticks - x0)
        d = float(arrival_ns - y0) - self.nominal * x
        index = (mcu_ticks - x0) // self.bin_ticks
        self._frames += 1
        k = self._kinds.get(kind)
        if k is None:
            if len(self._kinds) >= MAX_KINDS:
                del self._kinds[min(self._kinds, key=lambda key: self._kinds[key].last_seen)]
            self._kinds[kind] = _Kind(deque(maxlen=HISTORY_BINS), index, x, d, self._frames)
            return
        k.last_seen = self._frames
        if index == k.open_bin:
            if d < k.open_d:
                k.open_x, k.open_d = x, d
        elif index > k.open_bin:
            if k.opened:  # the kind's first second began mid-way: its minimum is no floor
                k.bins.append((k.open_x, k.open_d))
            k.opened = True
            k.open_bin, k.open_x, k.open_d = index, x, d
        # A stamp from a second already closed (reordered, or a stale batch) adds nothing.

    def estimate(self) -> SkewEstimate | None:
        """The common slope over the kinds with enough minima; None before there are any."""
        closed = sum(len(k.bins) for k in self._kinds.values())
        if self._cached[0] == closed:
            return self._cached[1]
        result = self._fit()
        self._cached = (closed, result)
        return result

    def _fit(self) -> SkewEstimate | None:
        """A robust slope first (the median of slopes between minima half the window apart),
        then each kind's minima within REJECT_SIGMAS of their robust scatter about it, fitted
        by least squares with one slope, an intercept per kind, each kind weighted by its
        scatter."""
        groups = [list(k.bins) for k in self._kinds.values() if len(k.bins) >= MIN_BINS]
        if not groups:
            return None
        spaced = [s for points in groups for s in _spaced_slopes(points)]
        if not spaced:
            return None
        rough = _median(spaced)
        kept: list[list[tuple[float, float]]] = []
        sigmas: list[float] = []
        rejected = 0
        for points in groups:
            level, sigma = _level_and_scatter(points, rough)
            limit = REJECT_SIGMAS * sigma
            good = [(x, d) for x, d in points if abs(d - rough * x - level) <= limit]
            rejected += len(points) - len(good)
            if len(good) >= MIN_BINS:
                kept.append(good)
                sigmas.append(sigma)
        num = info = 0.0
        for points, sigma in zip(kept, sigmas, strict=True):
            n = len(points)
            xm, dm = sum(x for x, _ in points) / n, sum(d for _, d in points) / n
            num += sum((x - xm) * (d - dm) for x, d in points) / sigma**2
            info += sum((x - xm) ** 2 for x, _ in points) / sigma**2
        if info <= 0.0:
            return None
        bins = sum(len(p) for p in kept)
        return SkewEstimate(self.nominal + num / info, VARIANCE_INFLATION / info, bins, rejected)


def _spaced_slopes(points: list[tuple[float, float]]) -> list[float]:
    """Slopes between each minimum and the one half the kind's window later."""
    half = len(points) // 2
    return [
        (d2 - d1) / (x2 - x1)
        for (x1, d1), (x2, d2) in zip(points, points[half:], strict=False)
        if x2 > x1
    ]


def _level_and_scatter(points: list[tuple[float, float]], slope: float) -> tuple[float, float]:
    """A kind's intercept (median) and robust σ (MAD, floored) about a line of that slope."""
    level = _median([d - slope * x for x, d in points])
    mad = _median([abs(d - slope * x - level) for x, d in points])
    return level, max(MAD_TO_SIGMA * mad, FLOOR_SIGMA_NS)


def _median(values: list[float]) -> float:
    """Middle value (upper middle for an even count): nothing here needs it finer."""
    return sorted(values)[len(values) // 2]
