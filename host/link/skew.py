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
squares, each kind with its own intercept and weighted by its own scatter. The fit reports the
slope's variance, so the clock sync can weigh it against its probes'. A floor that moved for
every kind at once (the host's USB latency, its load) looks like a rate error; it shows as the
window's recent half disagreeing with the whole by more than their noise explains, and that
excess is added to the variance, so the clock sync then leans on its probes instead.

Seconds are bins of 2^k controller ticks (2^20 µs at 1 MHz) counted from tick zero, not from the
first frame seen, so that a recording replayed from the middle of a session bins as the live
session did and, once its window has filled, fits the same line.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

BIN_S = 1.0  # about one minimum per kind per second (a power of two of ticks)
HISTORY_S = 120.0  # the window: minima older than this behind the newest are left out
MIN_BINS = 8  # a kind contributes once it has this many closed seconds in the window
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
    shift_variance: float = 0.0  # the part of `variance` a moved floor added


@dataclass
class _Kind:
    """The closed minima of one kind of frame, and the bin being filled."""

    bins: deque[tuple[int, int]]  # (extended ticks, arrival ns) of each closed bin's minimum
    open_bin: int
    open_x: int
    open_y: int
    last_seen: int
    opened: bool = False  # False while the open bin is the kind's first: it began mid-way


class SkewEnvelope:
    """Lower envelope of one-way delays, per kind of frame; one common slope."""

    def __init__(self, nominal_ns_per_tick: float) -> None:
        self.nominal = nominal_ns_per_tick
        ticks_per_s = 1e9 / nominal_ns_per_tick
        self.bin_ticks = 1 << max(0, round(math.log2(BIN_S * ticks_per_s)))
        self.window_ticks = round(HISTORY_S * ticks_per_s)
        self._history = math.ceil(self.window_ticks / self.bin_ticks) + 2  # bins a kind keeps
        self._kinds: dict[object, _Kind] = {}
        self._frames = 0
        self._newest_bin_x = 0  # the latest closed minimum's ticks, any kind
        self._version = 0  # moves whenever the fit's input does
        self._cached: tuple[int, SkewEstimate | None] = (-1, None)

    def add(self, kind: object, mcu_ticks: int, arrival_ns: int) -> None:
        """One frame: `kind` tells frames with different floors apart, `mcu_ticks` is extended."""
        index = mcu_ticks // self.bin_ticks
        self._frames += 1
        k = self._kinds.get(kind)
        if k is None:
            if len(self._kinds) >= MAX_KINDS:
                del self._kinds[min(self._kinds, key=lambda key: self._kinds[key].last_seen)]
                self._version += 1
            bins: deque[tuple[int, int]] = deque(maxlen=self._history)
            self._kinds[kind] = _Kind(bins, index, mcu_ticks, arrival_ns, self._frames)
            return
        k.last_seen = self._frames
        if index == k.open_bin:
            if self._delay(mcu_ticks, arrival_ns) < self._delay(k.open_x, k.open_y):
                k.open_x, k.open_y = mcu_ticks, arrival_ns
        elif index > k.open_bin:
            if k.opened:
                k.bins.append((k.open_x, k.open_y))
                self._newest_bin_x = max(self._newest_bin_x, k.open_x)
                self._version += 1
            k.opened = True
            k.open_bin, k.open_x, k.open_y = index, mcu_ticks, arrival_ns
        # A stamp from a bin already closed (reordered, or a stale batch) adds nothing.

    @property
    def frames(self) -> int:
        """Frames fed since the start (or the last reset)."""
        return self._frames

    def estimate(self) -> SkewEstimate | None:
        """The common slope over the kinds with enough minima; None before there are any."""
        if self._cached[0] != self._version:
            self._cached = (self._version, self._fit())
        return self._cached[1]

    def _delay(self, x: int, y: int) -> float:
        """Arrival less the nominal time of the stamp: delay plus offset, to compare minima."""
        return y - self.nominal * x

    def _fit(self) -> SkewEstimate | None:
        """The whole window's line; its variance grows by how far the recent half disagrees."""
        start = self._newest_bin_x - self.window_ticks
        whole = self._line(start)
        if whole is None:
            return None
        slope, variance, bins, rejected = whole
        recent = self._line(start + self.window_ticks // 2)
        shift = 0.0
        if recent is not None:
            # The recent half's minima are part of the whole's: while the floor holds still
            # the two slopes differ with variance recent − whole; beyond that it moved.
            shift = max(0.0, (recent[0] - slope) ** 2 - (recent[1] - variance))
        return SkewEstimate(self.nominal + slope, variance + shift, bins, rejected, shift)

    def _line(self, start_x: int) -> tuple[float, float, int, int] | None:
        """Slope over nominal, its variance, minima used and rejected, for minima from `start_x`.

        A robust slope first (the median of slopes between minima half the span apart), then
        each kind's minima within REJECT_SIGMAS of their robust scatter about it, fitted by
        least squares with one slope, an intercept per kind, each weighted by its scatter.
        """
        raw = [[p for p in k.bins if p[0] >= start_x] for k in self._kinds.values()]
        raw = [p for p in raw if len(p) >= MIN_BINS]
        if not raw:
            return None
        x0 = min(p[0][0] for p in raw)
        y0 = min(p[0][1] for p in raw)
        groups = [
            [(float(x - x0), float(y - y0) - self.nominal * (x - x0)) for x, y in p] for p in raw
        ]
        spaced = [s for points in groups for s in _spaced_slopes(points)]
        if not spaced:
            return None
        rough = _median(spaced)
        num = info = 0.0
        used = rejected = 0
        for points in groups:
            level, sigma = _level_and_scatter(points, rough)
            limit = REJECT_SIGMAS * sigma
            good = [(x, d) for x, d in points if abs(d - rough * x - level) <= limit]
            rejected += len(points) - len(good)
            if len(good) < MIN_BINS:
                continue
            n = len(good)
            xm, dm = sum(x for x, _ in good) / n, sum(d for _, d in good) / n
            num += sum((x - xm) * (d - dm) for x, d in good) / sigma**2
            info += sum((x - xm) ** 2 for x, _ in good) / sigma**2
            used += n
        if info <= 0.0:
            return None
        return num / info, VARIANCE_INFLATION / info, used, rejected


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
