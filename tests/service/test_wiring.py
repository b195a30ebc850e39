"""The daemon's pose feed: home offset, drift correction on reference marks, workpiece pose."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from host.config import Config, loads_config
from host.fusion.rig_references import chain_config, marks_sigma_mm
from host.registration.track_feed import DEFAULT_CHAIN_PITCH_MM, HEAD_STILL_NS, PoseFeed
from host.rig import RigSpec
from host.service.wiring import (
    STREAM_RATES_HZ,
    XBEE_SHEDDING,
    PosePublisher,
    apply_rig,
    build_pose_source,
    controller_factory,
    frame_loop_factory,
    rig_spec,
    workpiece_pose,
)
from protocol.enums import Inputs
from tests.rig.helpers import rig_config

STRETCH = 1.005  # a worn chain: 0.5 % longer than nominal
HOME_S_MM = 1000.0
MARKS_MM = (2000.0, 5000.0, 8000.0, 11000.0, 14000.0)
COUNT_MM = 0.05  # encoder resolution the synthetic marks are captured at
STEP_MM = 10.0  # controller travel between encoder samples
SAMPLE_NS = 5_000_000
HOMED = int(Inputs.HOMED)


def marked_config() -> Config:
    """The default runway with home and marks configured."""
    marks = ", ".join(str(m) for m in MARKS_MM)
    return rig_config(f"[track.home]\nvalue_mm = {HOME_S_MM}\n[track.marks]\ns_mm = [{marks}]\n")


def feed_spec() -> RigSpec:
    """The rig description of `marked_config`."""
    return rig_spec(marked_config())


def marked_feed(pitch_mm: float | None = 12.7) -> PoseFeed:
    """A feed on the default runway with home and marks configured."""
    _, feed = build_pose_source(
        marked_config(), STREAM_RATES_HZ["serial"], pitch_mm=lambda: pitch_mm
    )
    return feed


def drive(feed: PoseFeed, travel_mm: float, lap_mm: float) -> list[tuple[float, float, float]]:
    """Move the stretched chain; (true s, fused s, raw s) per sample after the second mark."""
    after_two: list[tuple[float, float, float]] = []
    crossings = 0
    for i in range(round(travel_mm / STEP_MM) + 1):
        s_ctrl, s_next = i * STEP_MM, (i + 1) * STEP_MM
        feed.on_encoder(i * SAMPLE_NS, s_ctrl, 2000.0, HOMED)
        if crossings >= 2:
            true = HOME_S_MM + STRETCH * s_ctrl
            after_two.append((true, feed.s_mm or 0.0, feed.raw_s_mm or 0.0))
        for mark in _marks_between(
            HOME_S_MM + STRETCH * s_ctrl, HOME_S_MM + STRETCH * s_next, lap_mm
        ):
            captured = round((mark - HOME_S_MM) / STRETCH / COUNT_MM) * COUNT_MM
            feed.on_mark(i * SAMPLE_NS + 1, captured)
            crossings += 1
    return after_two


def _marks_between(lo_mm: float, hi_mm: float, lap_mm: float) -> list[float]:
    """Unwrapped positions of the marks passed between two true arc lengths."""
    laps = range(math.floor(lo_mm / lap_mm), math.floor(hi_mm / lap_mm) + 1)
    return [m + k * lap_mm for k in laps for m in MARKS_MM if lo_mm <= m + k * lap_mm < hi_mm]


def test_stretched_chain_is_corrected_after_two_marks() -> None:
    feed = marked_feed()
    lap_mm = feed.lap_mm or 0.0
    assert lap_mm == pytest.approx(2 * (4000 + 1000) + 2 * math.pi * 1000)
    samples = drive(feed, 21_000.0, lap_mm)  # 1.4 laps: marks of the second lap too
    worst_fused = max(abs(fused - true) for true, fused, _ in samples)
    assert worst_fused < 0.5
    true, _, raw = samples[-1]
    assert raw - HOME_S_MM == pytest.approx(21_000.0)  # the raw one is the controller's + home
    assert true - raw == pytest.approx(0.005 * 21_000.0, abs=1e-6)  # 105 mm off after 21 m
    assert feed.encoder.window()[1][-1][0] == pytest.approx(feed.s_mm)  # the buffer holds fused
    stats = feed.stats()
    assert stats["chain_scale"] == pytest.approx(STRETCH, abs=2e-5)
    assert stats["marks_seen"] == stats["references_used"] == 7  # five, then two on the next lap
    assert (
        stats["references_rejected"] == stats["marks_unassociated"] == stats["skips_detected"] == 0
    )
    # the rig file's marks σ (1 mm ⊕ the home's 1 mm), narrowed by the references: an exact
    # synthetic mark does not make the filter claim more than the survey gives
    assert 0.3 < stats["position_sigma_mm"] < marks_sigma_mm(feed_spec())
    assert stats["raw_s_mm"] == pytest.approx(raw)


def test_without_marks_the_feed_only_adds_home() -> None:
    config = rig_config("[track.home]\nvalue_mm = 250.5\n")
    _, feed = build_pose_source(config, STREAM_RATES_HZ["can"])
    assert feed.chain is None
    feed.on_encoder(1_000, 100.0, 0.0, 0)
    feed.on_mark(2_000, 100.0)  # counted, nothing to correct against
    assert feed.s_mm == feed.raw_s_mm == pytest.approx(350.5)
    assert feed.stats() == {
        "track_s_mm": 350.5,
        "raw_s_mm": 350.5,
        "marks_seen": 1,
        "homed": False,
        "zero_resets": 0,
    }


def test_chain_pitch_follows_identify_until_the_first_reference() -> None:
    pitch: list[float | None] = [None]
    config = rig_config("[track.marks]\ns_mm = [500.0, 1500.0]\n")
    _, feed = build_pose_source(config, STREAM_RATES_HZ["xbee"], pitch_mm=lambda: pitch[0])
    assert feed.chain is not None
    assert feed.chain.config.chain_pitch_mm == DEFAULT_CHAIN_PITCH_MM
    feed.on_encoder(500, 0.0, 0.0, HOMED)
    pitch[0] = 15.875  # the controller identified itself: an ANSI 50 chain
    feed.on_mark(1_000, 499.0)
    assert feed.chain.config.chain_pitch_mm == 15.875
    assert feed.chain.stats.updates == 1
    pitch[0] = 9.525  # a later change must not throw away what the filter learned
    feed.on_mark(2_000, 1497.0)
    assert feed.chain.config.chain_pitch_mm == 15.875
    assert feed.chain.stats.updates == 2


def test_far_mark_is_unassociated_not_applied() -> None:
    feed = marked_feed()
    feed.on_encoder(0, 0.0, 0.0, HOMED)
    feed.on_mark(1, 2500.0)  # predicted 3500: 1500 mm from the nearest mark
    assert feed.chain is not None
    assert feed.stats()["marks_unassociated"] == 1
    assert feed.stats()["references_used"] == 0
    feed.on_encoder(2, 10.0, 0.0, HOMED)
    assert feed.s_mm == pytest.approx(HOME_S_MM + 10.0)


def test_marks_count_only_after_homing_and_rehoming_starts_afresh() -> None:
    feed = marked_feed()
    feed.on_encoder(0, 995.0, 0.0, 0)  # power-up: the zero is wherever the trolley stood
    feed.on_mark(1, 995.0)
    assert feed.stats()["marks_unhomed"] == 1
    assert feed.stats()["references_used"] == 0
    feed.on_encoder(2, 0.0, 0.0, HOMED)
    feed.on_mark(3, (MARKS_MM[0] - HOME_S_MM) / STRETCH)
    assert feed.chain is not None
    assert feed.chain.x[1] > 1.001  # the stretch shows
    before = feed.chain
    feed.on_encoder(4, 0.0, 0.0, HOMED)
    assert feed.chain is before  # still homed: the filter keeps what it learned
    feed.on_encoder(5, 0.0, 0.0, 0)  # HOME again: the encoder is re-referenced
    feed.on_encoder(6, 0.0, 0.0, HOMED)
    assert feed.chain is not before
    assert feed.stats()["references_used"] == 0
    assert feed.stats()["chain_scale"] == 1.0


def test_workpiece_pose_from_the_rig_file() -> None:
    config = rig_config(
        "[workpiece.frame]\nmatrix = [[0, -1, 0, 1000], [1, 0, 0, -250.5], [0, 0, 1, 12], "
        "[0, 0, 0, 1]]\n"
    )
    T_w_p = workpiece_pose(config)
    assert np.allclose(T_w_p[:3, 3], [1000.0, -250.5, 12.0])
    assert np.allclose(T_w_p[:3, :3] @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])  # x_p along y_w
    assert np.allclose(workpiece_pose(Config()), np.eye(4))


def test_factory_wires_the_feed_into_link_stats() -> None:
    rig = "[track.home]\nvalue_mm = 100.0\n[track.marks]\ns_mm = [3000.0]\n"
    config = rig_config(rig, '[camera]\nsource = "none"\n')
    taps: list[Any] = []
    controller = controller_factory(config, lambda *rec: taps.append(rec))
    assert controller.chain_pitch_mm() is None  # no handshake yet
    loop = frame_loop_factory(config, controller, lambda pose: None, lambda *rec: None)
    assert isinstance(loop, PosePublisher)
    feed = next(sink for sink in controller.sinks if isinstance(sink, PoseFeed))
    feed.on_encoder(1_000, 42.0, 0.0, 0)
    stats = controller.link_stats()
    assert stats["raw_s_mm"] == pytest.approx(142.0)
    assert stats["chain_scale"] == 1.0
    assert stats["marks_seen"] == 0


def test_surveyed_surfaces_give_the_feed_rangefinder_fixes() -> None:
    config = rig_config(
        "[track.home]\nvalue_mm = 100.0\n"
        "[[hall.surfaces]]\nname = 'east wall'\npoint_mm = [6000, 0, 0]\n"
        "normal = [-1, 0, 0]\n"
    )
    source, feed = build_pose_source(config, STREAM_RATES_HZ["serial"])
    assert feed.ranger is not None
    assert feed.chain is not None
    # the daemon's filter is the one the demo measures: the rig file's σ, the range model's
    # parameters held as states
    spec = rig_spec(config)
    assert feed.chain.config == chain_config(spec, DEFAULT_CHAIN_PITCH_MM)
    bias = feed.chain.config.bias_cov
    assert bias is not None
    assert feed.chain.biases == bias.shape[0] > 0
    np.testing.assert_array_equal(source.rig.T_r_l, np.eye(4))
    # The beam level along the first straight: the east wall is 8 m - s ahead.
    for i in range(40):
        t = i * SAMPLE_NS
        feed.on_encoder(t, i * STEP_MM, 2000.0, HOMED)
        feed.on_head(t, 0.0, math.pi / 2)
        true_s = 100.0 + STRETCH * i * STEP_MM
        feed.on_range(t + 1, 8000.0 - true_s, 200)
    feed.on_head(t + HEAD_STILL_NS + 1, 0.0, math.pi / 2)  # past the last reading: all decided
    assert feed.ranger.stats.fixes == 40
    assert feed.s_mm == pytest.approx(100.0 + STRETCH * 39 * STEP_MM, abs=0.2)
    assert feed.stats()["range_fixes"] == 40


def test_the_daemon_sheds_telemetry_on_xbee_only() -> None:
    xbee = loads_config(
        '[link]\nkind = "xbee"\nurl = "/dev/ttyUSB0"\nxbee_address = "0013A20040A1B2C3"\n'
        '[camera]\nsource = "none"\n'
    )
    controller = controller_factory(xbee, lambda *rec: None)
    assert controller.shedding is XBEE_SHEDDING
    assert controller.link_stats()["telemetry_scale"] == 1.0
    serial = controller_factory(loads_config('[camera]\nsource = "none"\n'), lambda *rec: None)
    assert serial.shedding is None


def test_a_reread_rig_file_keeps_the_running_filter_unless_its_references_changed() -> None:
    config = marked_config()
    source, feed = build_pose_source(config, STREAM_RATES_HZ["serial"], pitch_mm=lambda: 12.7)
    running = feed.chain
    assert running is not None
    apply_rig(config, source, feed, 0.0)  # SIGHUP, nothing changed: the state is kept
    assert feed.chain is running
    marks = ", ".join(str(m) for m in MARKS_MM)
    surveyed = rig_config(
        f"[track.home]\nvalue_mm = {HOME_S_MM}\n[track.marks]\ns_mm = [{marks}]\nsigma_mm = 0.3\n"
    )
    apply_rig(surveyed, source, feed, 0.0)  # a marks survey wrote new σ: a fresh filter on them
    assert feed.chain is not running
    assert feed.chain is not None
    assert feed.chain.config == chain_config(rig_spec(surveyed), 12.7)
