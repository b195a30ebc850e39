"""RigIO's head angles for a frame taken at rest."""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np
import pytest

from host.commissioning.frames import FrameTap
from host.commissioning.motion import RestReadings, RigIO
from host.control.api import ControllerLike

COUNT_RAD = 1e-4


def _io() -> RigIO:
    return RigIO(cast(ControllerLike, object()), cast(FrameTap, object()))


def test_a_flickered_reading_at_rest_is_not_the_views_angle() -> None:
    io = _io()
    readings = [(0.3, -0.2)] * 6 + [(0.3 + COUNT_RAD, -0.2 - COUNT_RAD)] + [(0.3, -0.2)] * 3
    io.rest_head_rad = np.array(readings)
    snap: dict[str, Any] = {"head_rad": [0.3 + COUNT_RAD, -0.2 - COUNT_RAD]}  # the flicker
    assert io.head_at_rest(snap) == pytest.approx((0.3, -0.2), abs=1e-15)


def test_rest_readings_either_side_of_the_pan_stop() -> None:
    io = _io()
    io.rest_head_rad = np.array(
        [(math.pi - 2e-5, 0.0), (-math.pi + 2e-5, 0.0), (math.pi - 2e-5, 0.0)]
    )
    pan, _ = io.head_at_rest({})
    assert math.remainder(pan - (math.pi - 2e-5), math.tau) == pytest.approx(0.0, abs=1e-12)


def test_without_rest_readings_the_snapshot_is_taken() -> None:
    io = _io()
    assert io.head_at_rest({"head_rad": [0.1, 0.2]}) == (0.1, 0.2)
    pan, tilt = io.head_at_rest({})
    assert math.isnan(pan)
    assert math.isnan(tilt)


def test_rest_readings_take_each_head_sample_once() -> None:
    rest = RestReadings()
    # polls every 20 ms, head samples every 50 ms (sample k at 50 k ms, a flicker at k = 2)
    for poll in range(15):
        now = 0.02 * poll + 0.001
        k = int(now / 0.05)
        pan = 0.3 + (COUNT_RAD if k == 2 else 0.0)
        rest.take({"head_rad": [pan, -0.2], "head_age_s": round(now - 0.05 * k, 6)}, now)
    assert len(rest.readings) == 6  # samples 0…5
    assert [p for p, _ in rest.readings].count(0.3 + COUNT_RAD) == 1


def test_rest_readings_without_the_samples_age_take_every_poll() -> None:
    rest = RestReadings()
    for poll in range(4):
        rest.take({"head_rad": [0.3, -0.2]}, 0.02 * poll)
    rest.take({"head_rad": None, "head_age_s": 0.0}, 1.0)  # no head yet: nothing
    assert len(rest.readings) == 4
