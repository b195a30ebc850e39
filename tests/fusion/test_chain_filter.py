"""The drift-correction filter against synthetic chain elongation and tooth skips."""

from __future__ import annotations

import numpy as np
import pytest

from host.fusion.chain_filter import ChainFilter, ChainFilterConfig

PITCH_MM = 12.7
LOOP_MM = 16283.185


def _drive(
    elongation: float, skips_at_mm: dict[float, int], marks: tuple[float, ...], seed: int = 1
) -> tuple[ChainFilter, list[tuple[float, float, float]]]:
    """Travel one loop; return the filter and (true, encoder-only, fused) positions."""
    rng = np.random.default_rng(seed)
    filt = ChainFilter(ChainFilterConfig(chain_pitch_mm=PITCH_MM))
    trace = []
    jumps = 0.0
    for enc in np.arange(0.0, LOOP_MM / (1 + elongation), 5.0):
        for at, teeth in skips_at_mm.items():
            if at <= enc < at + 5.0:
                jumps += teeth * PITCH_MM
        true = enc * (1 + elongation) + jumps
        for mark in marks:
            if abs(true - mark) < 2.5 * (1 + elongation):
                enc_at_mark = (mark - jumps) / (1 + elongation) + rng.normal(0, 0.05)
                found = filt.associate(enc_at_mark, marks)
                if found is not None:
                    filt.reference(enc_at_mark, found)
        filt.predict(enc)
        trace.append((true, enc, filt.estimate(enc)[0]))
    return filt, trace


def test_elongation_is_learnt_from_references() -> None:
    marks = tuple(float(m) for m in range(2000, 16000, 2000))
    filt, trace = _drive(0.005, {}, marks)
    true, enc, fused = np.array(trace).T
    late = true > 4000
    assert np.max(np.abs(enc - true)[late]) > 20.0  # encoder-only drifts by metres × 0.5 %
    assert np.max(np.abs(fused - true)[late]) < 1.0
    assert filt.x[1] == pytest.approx(1.005, abs=2e-4)


def test_tooth_skip_is_detected_and_corrected_at_the_next_mark() -> None:
    marks = tuple(float(m) for m in range(2000, 16000, 2000))
    filt, trace = _drive(0.005, {7000.0: 1}, marks)
    true, _, fused = np.array(trace).T
    after_next_mark = true > 8100
    assert filt.stats.skips_detected == 1
    assert np.max(np.abs(fused - true)[after_next_mark]) < 1.0


def test_reference_far_from_any_mark_is_not_associated() -> None:
    filt = ChainFilter()
    assert filt.associate(5000.0, (1000.0, 9000.0)) is None
    assert filt.stats.unassociated == 1


def test_gross_outlier_is_rejected_and_leaves_the_state() -> None:
    filt = ChainFilter()
    before = filt.x.copy()
    assert not filt.reference(1000.0, 1000.0 + 150.0)
    assert filt.stats.rejected == 1
    np.testing.assert_array_equal(filt.x, before)


def test_uncertainty_shrinks_with_references() -> None:
    filt = ChainFilter()
    _, sigma_before = filt.estimate(8000.0)
    filt.reference(4000.0, 4010.0)
    filt.reference(8000.0, 8040.0)
    _, sigma_after = filt.estimate(8000.0)
    assert sigma_after < sigma_before / 10
