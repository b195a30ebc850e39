"""The latency run's clock-sync σ: the link's estimator's own, measured while it runs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from host.calibration.board import BoardSpec, Detection
from host.commissioning.latency_run import LatencyThresholds, PassFrame, judge, latency_update
from host.commissioning.ops import _clock_sigma_ms
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray, make_T
from host.link.clocksync import ClockSync

US = 1_000


def fed_clock(round_trip_ns: list[int]) -> ClockSync:
    """A clock fed 10 Hz probes with these round trips (symmetric legs, no residence)."""
    clock = ClockSync()
    for k, rtt in enumerate(round_trip_ns):
        t0 = 1_000_000_000 + k * 100_000_000
        mcu_us = (t0 + rtt // 2) // US
        clock.add_probe(t0, mcu_us, t0 + rtt, mcu_us)
    return clock


def test_no_session_or_no_fit_gives_none() -> None:
    """A controller without a link, or a clock without a probe yet: nothing measured."""
    assert _clock_sigma_ms(object()) is None
    assert _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=ClockSync()))) is None


def test_the_estimators_uncertainty_in_ms() -> None:
    """The σ is the estimator's own uncertainty, converted to milliseconds."""
    clock = fed_clock([5_000_000 + (k % 7) * 300_000 for k in range(60)])
    got = _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=clock)))
    assert got == pytest.approx(clock.uncertainty_ns() / 1e6)
    assert got is not None
    assert got > 0.0


def test_slower_round_trips_give_a_larger_sigma() -> None:
    """A loaded link (round trips spread by milliseconds) is trusted less than a quiet one."""
    quiet = fed_clock([5_000_000 + (k % 7) * 20_000 for k in range(60)])
    loaded = fed_clock([5_000_000 + (k % 7) * 1_500_000 for k in range(60)])
    q = _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=quiet)))
    lo = _clock_sigma_ms(SimpleNamespace(session=SimpleNamespace(clock=loaded)))
    assert q is not None
    assert lo is not None
    assert lo > q


def passes_past_a_board(delay_ms: float) -> tuple[list[PassFrame], Rig, CameraModel, FloatArray]:
    """Frames of two passes at ±300 mm/s past a board, stamped `delay_ms` late (no noise)."""
    rig, camera = Rig(), CameraModel()
    s0, pan, tilt = 1700.0, 0.0, -0.3
    T_w_c = rig.T_w_c(s0, pan, tilt)
    board = BoardSpec()
    T_c_b = make_T(np.eye(3), np.array([0.0, 0.0, 3000.0]) - board.centre_mm)
    T_w_b = T_w_c @ T_c_b
    X = np.asarray(board.make().getChessboardCorners(), np.float64).reshape(-1, 3)
    frames = []
    for v in (300.0, -300.0):
        for k in range(-7, 8):
            s_true = s0 + 5.0 * k
            uv, _ = camera.project_world(rig.T_c_w(s_true, pan, tilt) @ T_w_b, X)
            det = Detection(np.arange(len(X), dtype=np.int32), X, uv, 1.0)
            frames.append(PassFrame(k, det, s_true + v * delay_ms / 1e3, pan, tilt, v))
    return frames, rig, camera, T_w_b


def test_the_clocks_sigma_is_reported_not_failed() -> None:
    """A loaded link's clock σ goes into the written σ; the verdict judges what the passes
    measured (more passes cannot shrink the clock's error)."""
    frames, rig, camera, T_w_b = passes_past_a_board(20.0)
    limits = LatencyThresholds()
    quiet = judge(frames, rig, camera, T_w_b, 0.0, limits, clock_sigma_ms=0.25)
    loaded = judge(frames, rig, camera, T_w_b, 0.0, limits, clock_sigma_ms=3.0)
    assert quiet.passed
    assert loaded.passed
    assert quiet.new_ms == pytest.approx(20.0, abs=0.01)
    assert loaded.sigma_ms >= 3.0


def test_a_latency_no_camera_can_have_fails_and_says_why() -> None:
    """Frames that read as stamped 40 ms before their exposure (what a jump of the arc length
    during the passes once gave): refused, with the reason; a latency near 0 still passes."""
    limits = LatencyThresholds()
    impossible = judge(*passes_past_a_board(-40.0), 0.0, limits, clock_sigma_ms=0.5)
    assert not impossible.passed
    assert "cannot be stamped before its exposure" in impossible.reasons[0]
    with pytest.raises(ValueError, match="only a passing calibration"):
        latency_update(impossible)
    triggered = judge(*passes_past_a_board(-0.5), 0.0, limits, clock_sigma_ms=0.5)
    assert triggered.passed  # within 3 σ of a trigger's stamp at the exposure
