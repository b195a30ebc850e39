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


def _settled(scale: float = 1.005) -> ChainFilter:
    """A filter that has learnt the chain from references every 500 mm over 5 m."""
    filt = ChainFilter(ChainFilterConfig(chain_pitch_mm=PITCH_MM))
    for enc in np.arange(0.0, 5000.0, 500.0):
        assert filt.reference(float(enc), float(enc) * scale)
    return filt


def test_a_skip_moves_the_offset_by_one_true_pitch_and_leaves_the_scale() -> None:
    filt = _settled()
    scale_before = float(filt.x[1])
    enc = 5200.0
    assert filt.reference(enc, enc * 1.005 + PITCH_MM * 1.005)
    assert filt.stats.skips_detected == 1
    assert filt.x[1] == pytest.approx(scale_before, abs=1e-7)
    assert filt.estimate(6000.0)[0] == pytest.approx(6000.0 * 1.005 + PITCH_MM * 1.005, abs=0.05)


def test_a_coarse_reference_cannot_call_a_skip() -> None:
    filt = _settled()
    enc = 5200.0
    # σ 3 mm: one pitch and the next are within 4σ of each other, so this is refused.
    assert not filt.reference(enc, enc * 1.005 + PITCH_MM * 1.005, sigma_mm=3.0)
    assert filt.stats.skips_detected == 0
    assert filt.stats.rejected == 1


def test_a_stray_reading_mimicking_a_skip_is_undone_by_the_next_good_one() -> None:
    filt = _settled()
    assert filt.reference(5200.0, 5200.0 * 1.005 + PITCH_MM * 1.005, sigma_mm=1.0)
    assert filt.reference(5210.0, 5210.0 * 1.005, sigma_mm=1.0)
    assert filt.stats.skips_detected == 2
    assert filt.estimate(6000.0)[0] == pytest.approx(6000.0 * 1.005, abs=0.1)


def test_an_older_reference_does_not_count_its_travel_twice() -> None:
    filt = _settled()
    filt.predict(5100.0)
    p_before = filt.p.copy()
    filt.reference(5095.0, 5095.0 * 1.005, sigma_mm=1e6, advance=False)  # no information
    np.testing.assert_allclose(filt.p, p_before, rtol=1e-6)


def test_correct_maps_many_readings_like_estimate() -> None:
    filt = _settled()
    enc = np.array([0.0, 1234.5, 9999.0])
    expected = [filt.estimate(float(e))[0] for e in enc]
    np.testing.assert_allclose(filt.correct(enc), expected)


def test_coarse_references_that_agree_on_a_skip_decide_it_together() -> None:
    filt = _settled()
    jumped = PITCH_MM * 1.005
    for k in range(3):  # σ 3 mm each: none alone can tell one pitch from the next
        enc = 5200.0 + k
        assert not filt.reference(enc, enc * 1.005 + jumped, sigma_mm=3.0)
    assert filt.stats.skips_detected == 0
    for k in range(3, 12):
        enc = 5200.0 + k
        if filt.reference(enc, enc * 1.005 + jumped, sigma_mm=3.0):
            break
    assert filt.stats.skips_detected == 1
    assert filt.estimate(6000.0)[0] == pytest.approx(6000.0 * 1.005 + jumped, abs=1.0)


def test_a_good_reference_in_between_clears_the_pooled_evidence() -> None:
    filt = _settled()
    jumped = PITCH_MM * 1.005
    for k in range(3):
        filt.reference(5200.0 + k, (5200.0 + k) * 1.005 + jumped, sigma_mm=3.0)
    assert filt.reference(5204.0, 5204.0 * 1.005, sigma_mm=3.0)  # no skip after all
    for k in range(5, 8):
        assert not filt.reference(5200.0 + k, (5200.0 + k) * 1.005 + jumped, sigma_mm=3.0)
    assert filt.stats.skips_detected == 0


def _biased_run(bias_cov: np.ndarray | None, skip_at_mm: float | None = None) -> ChainFilter:
    """Fixes every 5 mm that all read 1.5 mm long (one shared bias, σ 0.5 mm of noise), and a
    sharp mark (σ 0.1 mm) every metre; 0.5 % stretch, an optional tooth skip."""
    rng = np.random.default_rng(3)
    config = ChainFilterConfig(chain_pitch_mm=PITCH_MM, bias_cov=bias_cov)
    filt = ChainFilter(config)
    jump = 0.0
    for enc in np.arange(5.0, 4000.0, 5.0):
        if skip_at_mm is not None and enc >= skip_at_mm:
            jump = PITCH_MM * 1.005
        true = enc * 1.005 + jump
        if enc % 1000.0 < 5.0:
            filt.reference(enc, true, 0.1)  # a mark: no bias
        g = None if bias_cov is None else np.array([1.0])
        filt.reference(enc, true + 1.5 + rng.normal(0.0, 0.5), 0.5, gradient=g)
    return filt


def test_a_bias_the_references_share_is_a_state_not_noise() -> None:
    """Taken as independent noise, hundreds of fixes outvote the marks and pull the position
    by their shared bias; held as a state, the bias is learnt and the marks keep the position."""
    naive, held = _biased_run(None), _biased_run(np.array([[2.0**2]]))
    assert naive.estimate(4000.0)[0] - 4000.0 * 1.005 > 1.0
    assert held.biases == 1
    assert held.estimate(4000.0)[0] == pytest.approx(4000.0 * 1.005, abs=0.1)
    assert held.x[2] == pytest.approx(1.5, abs=0.1)


def test_a_skip_is_found_through_a_shared_bias() -> None:
    filt = _biased_run(np.array([[2.0**2]]), skip_at_mm=2500.0)
    assert filt.stats.skips_detected == 1
    assert filt.stats.rejected == 0
    assert filt.estimate(3995.0)[0] == pytest.approx(3995.0 * 1.005 + PITCH_MM * 1.005, abs=0.1)
    assert filt.x[2] == pytest.approx(1.5, abs=0.1)
