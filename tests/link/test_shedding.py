"""The shedder's arithmetic: cut on a lossy window, floor, give back after a clean stretch."""

from __future__ import annotations

import pytest

from host.link.shedding import Shedder, SheddingConfig

CFG = SheddingConfig(window_s=1.0, loss_above=0.05, min_frames=20, cut=0.5, floor=0.125)


def test_a_lossy_window_halves_the_rates_down_to_the_floor() -> None:
    shedder = Shedder(CFG)
    assert shedder.observe(received=90, lost=10)
    assert shedder.scale == 0.5
    assert shedder.observe(90, 10)
    assert shedder.observe(90, 10)
    assert shedder.scale == 0.125
    assert not shedder.observe(90, 10)  # at the floor already
    assert shedder.scale == 0.125
    assert shedder.cuts == 3


def test_losses_at_the_threshold_and_sparse_windows_change_nothing() -> None:
    shedder = Shedder(CFG)
    assert not shedder.observe(received=95, lost=5)  # 5 %: not above
    assert not shedder.observe(received=5, lost=10)  # 15 frames: too few to judge
    assert shedder.scale == 1.0


def test_rates_come_back_a_step_per_clean_stretch() -> None:
    shedder = Shedder(CFG)
    shedder.observe(80, 20)
    shedder.observe(80, 20)
    assert shedder.scale == 0.25
    changes = [shedder.observe(100, 0) for _ in range(5)]
    assert changes == [False, False, False, False, True]
    assert shedder.scale == 0.375
    assert not shedder.observe(5, 0)  # a sparse window does not count as clean
    for _ in range(4):
        shedder.observe(100, 0)
    assert shedder.observe(80, 20)  # overload again before the next step: cut, count restarts
    assert shedder.scale == pytest.approx(0.1875)
    for _ in range(100):
        shedder.observe(100, 0)
    assert shedder.scale == 1.0
    assert not shedder.observe(100, 0)  # nothing above full rate


def test_scaled_rates_never_switch_a_stream_off() -> None:
    shedder = Shedder(CFG)
    for _ in range(3):
        shedder.observe(50, 50)
    assert shedder.rate(100) == 12  # 12.5 rounds to even
    assert shedder.rate(2) == 1
    assert shedder.rate(0) == 0


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="fractions"):
        SheddingConfig(cut=1.0)
    with pytest.raises(ValueError, match="clean_s"):
        SheddingConfig(window_s=2.0, clean_s=1.0)
