"""Homing moves the encoder's zero: no pose, and no drift reference, bridges the jump.

The firmware latches the index and sets HOMED in the same tick, so the first encoder sample that
says HOMED already carries the new count. The numbers follow a recorded HIL session: the last
unhomed sample at −337 mm on the track, the first homed one at +148 mm, 5 ms apart.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from host.control.api import PoseSample
from host.fusion.range_fix import RangeFixer
from host.registration.pose_buffer import AngleBuffer, LookupStatus, SampleBuffer
from host.registration.track_feed import PoseFeed
from host.service.wiring import STREAM_RATES_HZ, PosePublisher, build_pose_source
from protocol.enums import Inputs
from tests.fusion.test_range_fix import AHEAD, HALL, RIG, _reading
from tests.rig.helpers import rig_config

MS = 1_000_000
HOME_S_MM = 150.0
HOMED = int(Inputs.HOMED)
SAMPLE_NS = 5 * MS
T0_NS = 1_000 * MS
SEEK_MM_S = -150.0  # homing seeks toward negative s
LAST_UNHOMED_MM = -487.0  # controller mm from its power-up zero (−337 mm on the track)
FIRST_HOMED_MM = -2.0  # just past the index, from the new zero (+148 mm on the track)


def homing_samples() -> list[tuple[int, float, int]]:
    """(t, controller mm, inputs): seeking unhomed, then the latch, then back onto the index."""
    step_mm = SEEK_MM_S * SAMPLE_NS / 1e9
    out = [(T0_NS + k * SAMPLE_NS, LAST_UNHOMED_MM + (9 - k) * -step_mm, 0) for k in range(10)]
    t_latch = T0_NS + 10 * SAMPLE_NS
    out += [(t_latch + k * SAMPLE_NS, FIRST_HOMED_MM + 0.5 * k, HOMED) for k in range(5)]
    return out


def test_a_lookup_never_bridges_a_reset_of_the_zero() -> None:
    buf = SampleBuffer(1, capacity=64, horizon_ns=20 * MS)
    for i in range(3):
        buf.push(T0_NS + i * SAMPLE_NS, [-330.0 - i])
    t_reset = T0_NS + 3 * SAMPLE_NS
    buf.push(t_reset, [148.0], after_reset=True)
    mid = buf.lookup(t_reset - SAMPLE_NS // 2)
    assert mid.status is LookupStatus.STALE
    assert mid.value is None
    ahead = buf.lookup(t_reset + 2 * MS)  # one sample in its segment: carried, not extrapolated
    assert ahead.ok
    assert ahead.value is not None
    assert ahead.value[0] == 148.0
    before = buf.lookup(T0_NS + SAMPLE_NS // 2)  # inside the old segment all is as it was
    assert before.ok
    assert before.value is not None
    assert before.value[0] == pytest.approx(-330.5)
    buf.push(t_reset + SAMPLE_NS, [149.0])
    after = buf.lookup(t_reset + SAMPLE_NS // 2)
    assert after.ok
    assert after.value is not None
    assert after.value[0] == pytest.approx(148.5)


def test_a_reset_is_forgotten_once_the_samples_before_it_are() -> None:
    buf = SampleBuffer(1, capacity=4, horizon_ns=20 * MS)
    buf.push(0, [0.0])
    buf.push(SAMPLE_NS, [500.0], after_reset=True)
    for i in range(2, 6):  # the ring wraps: the pre-reset sample is gone
        buf.push(i * SAMPLE_NS, [500.0 + i])
    assert buf.lookup(SAMPLE_NS + 1).status is LookupStatus.STALE  # before the oldest kept
    t, _ = buf.window()
    assert all(buf.lookup(int(ti) + 1).ok for ti in t)
    buf.push(6 * SAMPLE_NS, [0.0], after_reset=True)
    buf.clear()
    buf.push(7 * SAMPLE_NS, [1.0])
    buf.push(8 * SAMPLE_NS, [2.0])
    assert buf.lookup(7 * SAMPLE_NS + 1).ok


class _Ctl:
    def snapshot(self) -> dict[str, Any]:
        return {"state": "HOMING"}


def test_no_pose_is_published_across_the_homing_latch() -> None:
    config = rig_config(f"[track.home]\nvalue_mm = {HOME_S_MM}\n[track.marks]\ns_mm = [250.0]\n")
    poses, feed = build_pose_source(config, STREAM_RATES_HZ["serial"])
    got: list[PoseSample] = []
    publisher = PosePublisher(poses, _Ctl(), got.append, 30.0)  # type: ignore[arg-type]
    samples = homing_samples()
    for t_ns, s_mm, inputs in samples:
        feed.on_encoder(t_ns, s_mm, 0.0, inputs)
        feed.on_head(t_ns, 0.0, 0.0)
        for ahead_ms in (1, 3):  # published live before the next sample arrives
            assert publisher.publish(t_ns + ahead_ms * MS)
    times = np.array([t for t, _, _ in samples])
    track = HOME_S_MM + np.array([s for _, s, _ in samples])
    homed = np.array([inputs for _, _, inputs in samples])
    for pose in got:  # within the samples of its own segment around it (carried ≤ 3 ms)
        i = int(np.searchsorted(times, pose.t_ns, side="right"))
        side = slice(i - 1, i + 1) if i < len(times) and homed[i] == homed[i - 1] else i - 1
        near = np.atleast_1d(track[side])
        assert near.min() - 0.5 <= pose.s_mm <= near.max() + 0.5, (pose.t_ns, pose.s_mm)
    # Looked up later (a frame's exposure, a late tick): between the two sides there is none.
    t_last_unhomed, t_latch = samples[9][0], samples[10][0]
    for t_ns in range(t_last_unhomed + MS, t_latch, MS):
        assert poses.pose_at(t_ns).status is LookupStatus.STALE
        assert not publisher.publish(t_ns)
    assert publisher.stale == 4
    assert feed.zero_resets == 1
    assert feed.stats()["zero_resets"] == 1


def test_a_reading_from_before_the_latch_is_no_reference_after_it() -> None:
    feed = PoseFeed(
        SampleBuffer(1, 256), AngleBuffer(2, 256), home_s_mm=HOME_S_MM, ranger=RangeFixer(RIG, HALL)
    )
    zero_off_mm = 3.0  # the power-up zero, 3 mm off home's index: inside every gate

    def true_s(k: int) -> float:
        return HOME_S_MM + 6.0 + SEEK_MM_S * k * SAMPLE_NS / 1e9

    for k in range(11):  # seeking, then the latch at k = 10 (the count jumps by 3 mm)
        homed = k == 10
        s_ctrl = true_s(k) - HOME_S_MM + (0.0 if homed else zero_off_mm)
        feed.on_encoder(T0_NS + k * SAMPLE_NS, s_ctrl, SEEK_MM_S, HOMED if homed else 0)
        feed.on_head(T0_NS + k * SAMPLE_NS, *AHEAD)
    # Readings stamped while unhomed, received after the latch: their encoder position is in the
    # old coordinates, so as references they would shift the new zero by 3 mm.
    for k in (8, 9):
        feed.on_range(T0_NS + k * SAMPLE_NS + MS, _reading(true_s(k)), 200)
    for k in (11, 12, 13, 14):  # the head's samples reach past them: now they are decided
        feed.on_encoder(T0_NS + k * SAMPLE_NS, true_s(k) - HOME_S_MM, SEEK_MM_S, HOMED)
        feed.on_head(T0_NS + k * SAMPLE_NS, *AHEAD)
    assert feed.ranges_unplaced == 2
    assert feed.chain is not None
    stats = feed.chain.stats
    assert (stats.updates, stats.rejected, stats.skips_detected) == (0, 0, 0)
    assert feed.s_mm == pytest.approx(true_s(14))


def test_the_uncorrected_arc_length_does_not_follow_a_tooth_skip() -> None:
    # The latency calibration times frames against the controller's count: a correction of
    # the chain filter (a skip it found, true or false) must not move it.
    mark_mm = HOME_S_MM + 500.0
    feed = PoseFeed(SampleBuffer(1, 512), AngleBuffer(2, 512), HOME_S_MM, marks_mm=(mark_mm,))
    pitch = 12.7
    times = [T0_NS + k * SAMPLE_NS for k in range(300)]
    for k, t in enumerate(times):  # 0.5 m/s from home; the mark read a pitch late (512.5 mm)
        feed.on_encoder(t, 2.5 * k, 500.0, HOMED)
        feed.on_head(t, 0.0, 0.0)
        if k == 205:
            feed.on_mark(t, 2.5 * k)
    t = times[-1]
    corrected = feed.encoder.lookup(t).value
    assert corrected is not None
    assert feed.chain is not None
    assert feed.chain.stats.updates >= 1
    assert abs(float(corrected[0]) - (HOME_S_MM + 2.5 * 299)) > pitch / 2  # the filter moved it
    assert feed.raw_at(t) == pytest.approx(HOME_S_MM + 2.5 * 299)  # the count did not move
    assert feed.raw_at(T0_NS - SAMPLE_NS * 100) is None  # before the samples kept
