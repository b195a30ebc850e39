"""Pose buffers (interpolation, horizon, bounded memory) and overlay drawing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.model import Wireframe, manipulator_wireframe
from host.geometry.transforms import invert_T, make_T, rot_z
from host.registration.overlay import OverlayStyle, WireframeOverlay, clip_segments
from host.registration.pose_buffer import (
    AngleBuffer,
    LookupStatus,
    PoseSource,
    SampleBuffer,
    TransformBuffer,
)

MS = 1_000_000


def linear_encoder(capacity: int = 64) -> SampleBuffer:
    """Encoder at 100 mm/s sampled every 1 ms from t = 1 s, s = 500 mm."""
    buf = SampleBuffer(1, capacity=capacity, horizon_ns=20 * MS)
    for i in range(50):
        buf.push(1000 * MS + i * MS, [500.0 + 0.1 * i])
    return buf


def test_interpolation_exact_for_linear_motion() -> None:
    buf = linear_encoder()
    for t_ns in (1000 * MS, 1000 * MS + 333_333, 1020 * MS + 1, 1049 * MS):
        r = buf.lookup(t_ns)
        assert r.status is LookupStatus.OK
        assert r.value is not None
        assert r.value[0] == pytest.approx(500.0 + 0.1 * (t_ns - 1000 * MS) / MS, abs=1e-9)


def test_extrapolation_within_horizon_then_stale() -> None:
    buf = linear_encoder()
    r = buf.lookup(1059 * MS)
    assert r.ok
    assert r.extrapolated_ns == 10 * MS
    assert r.value is not None
    assert r.value[0] == pytest.approx(505.9)
    late = buf.lookup(1049 * MS + 20 * MS + 1)
    assert late.status is LookupStatus.STALE
    assert late.value is None


def test_too_old_is_stale_and_empty_is_empty() -> None:
    buf = linear_encoder(capacity=16)
    assert len(buf) == 16  # bounded: older samples were overwritten
    assert buf.lookup(1000 * MS).status is LookupStatus.STALE
    assert buf.lookup(1034 * MS).ok
    assert SampleBuffer(1).lookup(0).status is LookupStatus.EMPTY


def test_gap_and_out_of_order_samples() -> None:
    buf = SampleBuffer(1, max_gap_ns=50 * MS)
    buf.push(0, [0.0])
    buf.push(200 * MS, [10.0])
    assert buf.lookup(100 * MS).status is LookupStatus.STALE  # would bridge a 200 ms hole
    assert not buf.push(150 * MS, [5.0])
    assert buf.rejected == 1


def test_ring_wraps_many_times_and_stays_ordered() -> None:
    buf = SampleBuffer(2, capacity=5)
    for i in range(23):
        buf.push(i * MS, [i, -i])
    t, v = buf.window()
    assert t.tolist() == [m * MS for m in range(18, 23)]
    assert v[:, 0].tolist() == [18, 19, 20, 21, 22]
    r = buf.lookup(int(20.5 * MS))
    assert r.value is not None
    np.testing.assert_allclose(r.value, [20.5, -20.5])


def test_revise_rewrites_only_samples_from_a_time_on_across_the_ring_seam() -> None:
    buf = SampleBuffer(1, capacity=8)
    for k in range(13):  # wrapped: the retained window straddles the end of the ring
        buf.push(k * 10, [float(k)])
    seen: list[int] = []

    def plus_100(times: np.ndarray) -> np.ndarray:
        seen.extend(int(t) for t in times)
        return times / 10.0 + 100.0

    assert buf.revise(95, plus_100) == 3
    assert seen == [100, 110, 120]
    _t, v = buf.window()
    np.testing.assert_array_equal(v[:, 0], [5, 6, 7, 8, 9, 110, 111, 112])
    mid = buf.lookup(115).value
    assert mid is not None
    assert mid[0] == pytest.approx(111.5)
    assert buf.revise(1000, plus_100) == 0


def test_angle_buffer_interpolates_across_pi() -> None:
    buf = AngleBuffer(2)
    buf.push(0, [math.pi - 0.1, 0.0])
    buf.push(10, [-math.pi + 0.1, 0.2])
    r = buf.lookup(5)
    assert r.value is not None
    assert abs(math.remainder(r.value[0] - math.pi, 2 * math.pi)) < 1e-12
    assert r.value[1] == pytest.approx(0.1)


def test_transform_buffer_slerps() -> None:
    buf = TransformBuffer()
    buf.push_T(0, make_T(rot_z(0.0), [0, 0, 0]))
    buf.push_T(100, make_T(rot_z(1.0), [100, 0, 0]))
    r = buf.lookup_T(25)
    assert r.value is not None
    np.testing.assert_allclose(r.value, make_T(rot_z(0.25), [25, 0, 0]), atol=1e-12)
    ahead = TransformBuffer(horizon_ns=50)
    ahead.push_T(0, make_T(rot_z(0.0), [0, 0, 0]))
    ahead.push_T(100, make_T(rot_z(0.2), [10, 0, 0]))
    e = ahead.lookup_T(150)
    assert e.value is not None
    np.testing.assert_allclose(e.value, make_T(rot_z(0.3), [15, 0, 0]), atol=1e-12)


def test_pose_source_applies_exposure_latency() -> None:
    rig = Rig()
    enc = linear_encoder()
    head = AngleBuffer(2)
    head.push(1000 * MS, [0.1, -0.2])
    head.push(1049 * MS, [0.1, -0.2])
    src = PoseSource(rig, enc, head, exposure_latency_ns=10 * MS)
    p = src.pose_at(1030 * MS)
    assert p.ok
    assert p.s_mm == pytest.approx(502.0)
    assert p.T_w_c is not None
    np.testing.assert_allclose(p.T_w_c, rig.T_w_c(502.0, 0.1, -0.2))
    assert src.pose_at(990 * MS).status is LookupStatus.STALE
    manual = PoseSource(rig, enc, None, fixed_pan_rad=0.3)
    assert manual.pose_at(1010 * MS).pan_rad == 0.3


def test_overlay_draws_model_into_frame() -> None:
    rig, cam = Rig(), CameraModel()
    model = manipulator_wireframe()
    pan, tilt = rig.aim(1000.0, [0.0, 600.0, 800.0])
    T_c_w = rig.T_c_w(1000.0, pan, tilt)
    frame = np.zeros((cam.height, cam.width, 3), np.uint8)
    n = WireframeOverlay(cam, model).draw(frame, T_c_w, OverlayStyle((0, 255, 0), 1, True))
    assert n > 50
    drawn = frame[:, :, 1] > 0
    assert drawn.sum() > 1000
    assert not frame[:, :, 0].any()  # only the requested colour
    empty = np.zeros_like(frame)
    assert WireframeOverlay(cam, model).draw(empty, invert_T(rig.T_w_c(1000.0, 0, math.pi))) == 0


def test_edge_crossing_near_plane_is_clipped_not_wrapped() -> None:
    cam = CameraModel(k1=0.0, k2=0.0, skew=0.0)
    model = Wireframe(np.array([[0.0, 0.0, 2000.0], [0.0, 3000.0, -1000.0]]), np.array([[0, 1]]))
    seg = WireframeOverlay(cam, model).segments(np.eye(4))
    assert seg.shape == (1, 2, 2)
    # the visible part runs from the centre straight down (+v) to the image border
    assert seg[0, 0] == pytest.approx([cam.u0, cam.v0])
    assert seg[0, 1, 1] > cam.height - 1
    assert abs(seg[0, 1, 0] - cam.u0) < 1e-6


def test_clip_segments_to_rectangle() -> None:
    seg = np.array([[[-100.0, 50.0], [200.0, 50.0]], [[-5.0, -5.0], [-1.0, -9.0]]])
    out = clip_segments(seg, 100, 80, 0.0)
    assert out.shape == (1, 2, 2)
    np.testing.assert_allclose(out[0], [[0.0, 50.0], [99.0, 50.0]])


COUNT_RAD = 1e-4  # the simulated head's encoder count


def _head(values: list[float]) -> AngleBuffer:
    """A head buffer with these pan readings 20 ms apart (tilt 0)."""
    buf = AngleBuffer(2)
    for k, pan in enumerate(values):
        buf.push(k * 20 * MS, [pan, 0.0])
    return buf


def test_angle_buffer_drops_a_lone_flicker_at_rest() -> None:
    buf = _head([0.5, 0.5, 0.5 + COUNT_RAD, 0.5, 0.5])
    for t_ms in (30, 40, 50):  # either side of the flickered reading, and on it
        r = buf.lookup(t_ms * MS)
        assert r.value is not None
        assert r.value[0] == pytest.approx(0.5, abs=1e-15)


def test_angle_buffer_keeps_a_motion_as_read() -> None:
    # a slew speeding up, then at a constant rate: monotonic, so no sample moves, nothing lags
    pans = [0.01 * k**2 for k in range(6)] + [0.25 + 0.1 * k for k in range(1, 6)]
    buf = _head(pans)
    for k in range(len(pans) - 1):
        r = buf.lookup(k * 20 * MS + 10 * MS)
        assert r.value is not None
        assert r.value[0] == pytest.approx((pans[k] + pans[k + 1]) / 2, abs=1e-15)


def test_angle_buffer_holds_a_small_newest_step_until_confirmed() -> None:
    buf = _head([0.5, 0.5, 0.5 + COUNT_RAD])
    r = buf.lookup(40 * MS)  # on the newest: a count off the two before, not yet confirmed
    assert r.value is not None
    assert r.value[0] == pytest.approx(0.5, abs=1e-15)
    buf.push(60 * MS, [0.5 + COUNT_RAD, 0.0])  # confirmed: the head did move a count
    r = buf.lookup(40 * MS)
    assert r.value is not None
    assert r.value[0] == pytest.approx(0.5 + COUNT_RAD, abs=1e-15)
    big = _head([0.5, 0.5, 0.52])  # a slew's first step is taken as read
    r = big.lookup(40 * MS)
    assert r.value is not None
    assert r.value[0] == pytest.approx(0.52, abs=1e-15)


def test_angle_buffer_flicker_across_pi() -> None:
    buf = _head([math.pi - 1e-5, math.pi - 1e-5, -math.pi + 5e-5, math.pi - 1e-5, math.pi - 1e-5])
    r = buf.lookup(40 * MS)
    assert r.value is not None
    assert math.remainder(r.value[0] - (math.pi - 1e-5), 2 * math.pi) == pytest.approx(0, abs=1e-12)


def test_angle_buffer_median_stays_in_its_segment() -> None:
    buf = AngleBuffer(2)
    for t_ms, pan, reset in ((0, 0.4, False), (20, 0.4, False), (40, 0.5, True), (60, 0.45, False),
                             (80, 0.45, False)):  # fmt: skip
        buf.push(t_ms * MS, [pan, 0.0], after_reset=reset)  # a new zero from 40 ms on
    r = buf.lookup(40 * MS)  # its first sample: no neighbour before it in its segment
    assert r.value is not None
    assert r.value[0] == pytest.approx(0.5, abs=1e-15)
