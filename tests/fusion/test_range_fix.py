"""Rangefinder readings of surveyed walls as absolute track references, alone and in the feed."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.fusion.range_fix import RangeFixConfig, RangeFixer
from host.geometry.head import Rig
from host.geometry.rangefinder import RangeScene, hall_walls, range_at
from host.registration.pose_buffer import AngleBuffer, SampleBuffer
from host.registration.track_feed import PoseFeed
from protocol.enums import Inputs

RIG = Rig()
HALL = RangeScene(hall_walls((-6000.0, 6000.0), (-4500.0, 4500.0)))
AHEAD = (0.0, math.pi / 2)  # the beam level along the direction of travel
PITCH_MM = 12.7


def _reading(s_mm: float, pan: float = AHEAD[0], tilt: float = AHEAD[1]) -> float:
    hit = range_at(RIG, HALL, s_mm, pan, tilt)
    assert hit is not None
    return hit.distance_mm


@pytest.mark.parametrize("s_true", [1000.0, 3000.0, 4400.0, 4700.0, 8500.0])
@pytest.mark.parametrize("off_mm", [-12.7, -3.0, 0.4, 25.4])
def test_a_reading_is_inverted_to_the_true_position(s_true: float, off_mm: float) -> None:
    fixer = RangeFixer(RIG, HALL)
    fix = fixer.fix(s_true + off_mm, *AHEAD, _reading(s_true))
    assert fix is not None, fixer.stats
    assert fix.s_mm == pytest.approx(s_true, abs=0.01)
    assert 0.0 < fix.sigma_mm < 3.0 * fixer.config.noise_mm


def test_sigma_is_the_reading_sigma_over_the_sensitivity() -> None:
    fixer = RangeFixer(RIG, HALL, RangeFixConfig(noise_mm=2.0, head_sigma_rad=0.0))
    fix = fixer.fix(1000.0, *AHEAD, _reading(1000.0))
    assert fix is not None
    assert fix.sigma_mm == pytest.approx(2.0, rel=1e-6)  # straight, head-on: ∂r/∂s = -1
    assert fix.surface == "wall x+"


def test_a_beam_down_at_the_level_floor_says_nothing_about_s() -> None:
    fixer = RangeFixer(RIG, HALL)
    assert fixer.fix(1000.0, 0.0, 0.0, _reading(1000.0, 0.0, 0.0)) is None
    assert fixer.stats.weak == 1


def test_a_reading_far_from_the_prediction_is_not_this_surface() -> None:
    fixer = RangeFixer(RIG, HALL)
    assert fixer.fix(1000.0, *AHEAD, _reading(1000.0) - 400.0) is None
    assert fixer.stats.out_of_gate == 1


def test_no_echo_and_a_beam_into_a_hall_corner_are_refused_and_counted() -> None:
    fixer = RangeFixer(RIG, HALL)
    assert fixer.fix(1000.0, *AHEAD, None) is None
    corner = _corner_s()
    assert fixer.fix(corner, *AHEAD, _reading(corner)) is None
    assert fixer.stats.no_echo == 1
    assert fixer.stats.ambiguous + fixer.stats.grazing == 1


def _corner_s() -> float:
    """A track position on the first corner where the beam switches from one wall to the next."""
    s = np.arange(4000.0, 5571.0, 1.0)
    names = [range_at(RIG, HALL, float(x), *AHEAD) for x in s]
    surfaces = [h.surface if h else -1 for h in names]
    switch = next(i for i in range(1, len(s)) if surfaces[i] != surfaces[i - 1])
    return float(s[switch])


def _loop_feed(
    skip_at_mm: float, noise_mm: float = 1.0, late_ms: int = 0
) -> tuple[PoseFeed, list[tuple[int, float]]]:
    """Drive a feed through 6 m with 0.5 % stretch and one skip; return it and (t, true s).

    Readings reach the feed late_ms after their stamp (encoder samples at once).
    """
    rng = np.random.default_rng(3)
    feed = PoseFeed(
        SampleBuffer(1, 8192),
        AngleBuffer(2, 2048),
        home_s_mm=150.0,
        ranger=RangeFixer(RIG, HALL, RangeFixConfig(noise_mm=noise_mm)),
    )
    truth: list[tuple[int, float]] = []
    pending: list[tuple[int, float]] = []
    skipped = 0.0
    for k in range(int(12.0 * 1000)):  # 1 kHz for 12 s at 500 mm/s
        t_ns = k * 1_000_000
        true_s = 150.0 + 0.5 * k
        if true_s >= skip_at_mm and not skipped:
            skipped = PITCH_MM * 1.005
        true_s += skipped
        enc_rel = (0.5 * k) / 1.005  # the sprocket's view: stretch and skip unseen
        if k % 5 == 0:
            feed.on_encoder(t_ns, enc_rel, 500.0, int(Inputs.HOMED))
            truth.append((t_ns, true_s))
        if k % 20 == 0:
            feed.on_head(t_ns, *AHEAD)
        if k % 10 == 5:
            pending.append((t_ns, _reading(true_s) + rng.normal(0.0, noise_mm)))
        while pending and pending[0][0] + late_ms * 1_000_000 <= t_ns:
            feed.on_range(*pending.pop(0), 200)
    return feed, truth


def test_the_feed_follows_stretch_and_a_skip_from_wall_readings() -> None:
    feed, truth = _loop_feed(skip_at_mm=3000.0)
    assert feed.chain is not None
    assert feed.ranger is not None
    t, s = np.array(truth).T
    late = slice(-1500, None)  # the last 7.5 s: from 2.4 m on, across the skip and a corner
    fused = np.array([_value(feed.encoder, int(ti)) for ti in t[late]])
    error = np.abs(fused - s[late])
    # Only the samples between the skip and the next reading (10 ms: two samples) carry it.
    assert np.sum(error > 0.5) <= 2
    assert np.max(error[error < PITCH_MM / 2]) < 0.5
    assert feed.chain.stats.skips_detected == 1
    assert feed.chain.x[1] == pytest.approx(1.005, abs=2e-4)
    assert feed.ranger.stats.fixes > 500
    assert feed.stats()["range_fixes"] == feed.ranger.stats.fixes


def _value(buffer: SampleBuffer, t_ns: int) -> float:
    got = buffer.lookup(t_ns).value
    assert got is not None
    return float(got[0])


def test_a_fix_corrects_the_samples_buffered_after_its_stamp() -> None:
    feed, truth = _loop_feed(skip_at_mm=3000.0, late_ms=12)
    t, s = np.array(truth).T
    skip = int(np.flatnonzero(s >= 3000.0 + PITCH_MM)[0])
    # The first reading after the skip is stamped within 10 ms of it but arrives 12 ms later,
    # after encoder samples stamped since: those were pushed uncorrected and must be revised.
    fixed_from = skip + 2  # 10 ms on: past the first reading's stamp
    late = [
        _value(feed.encoder, int(ti)) - si
        for ti, si in zip(t[fixed_from:], s[fixed_from:], strict=True)
    ]
    assert np.max(np.abs(late[:6])) < 0.5
    assert feed.chain is not None
    assert feed.chain.stats.skips_detected == 1


def test_readings_near_an_open_tracks_ends_are_refused_not_raised() -> None:
    from host.geometry.track import Track

    straight = Track.from_config([{"kind": "straight", "length_mm": 3000.0}])
    rig = Rig(track=straight)
    fixer = RangeFixer(rig, HALL)
    for s in (0.2, 2999.8):
        hit = range_at(rig, HALL, s, *AHEAD)
        assert hit is not None
        assert fixer.fix(s, *AHEAD, hit.distance_mm) is None
    assert fixer.stats.off_track == 2
    assert fixer.fix(1500.0, *AHEAD, _hit_distance(rig, 1500.0)) is not None


def _hit_distance(rig: Rig, s: float) -> float:
    hit = range_at(rig, HALL, s, *AHEAD)
    assert hit is not None
    return hit.distance_mm
