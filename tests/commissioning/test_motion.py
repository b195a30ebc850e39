"""RigIO's head angles for a frame taken at rest."""

from __future__ import annotations

import math
from typing import Any, cast

import numpy as np
import pytest

from host.commissioning.frames import FrameTap
from host.commissioning.motion import RigIO
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
