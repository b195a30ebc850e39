"""The rangefinder's beam and the surveyed surfaces it reads."""

from __future__ import annotations

import math

import numpy as np
import pytest

from host.geometry.head import Rig
from host.geometry.rangefinder import RangeScene, Surface, beam_w, hall_walls, range_at
from host.geometry.track import RUNWAY_HEIGHT_MM

WALL = Surface("wall", (5000.0, 0.0, 0.0), (-2.0, 0.0, 0.0))


def test_a_beam_meets_a_wall_head_on_at_its_distance() -> None:
    hit = RangeScene((WALL,)).cast([1000.0, 200.0, 3000.0], [1.0, 0.0, 0.0])
    assert hit is not None
    assert hit.distance_mm == pytest.approx(4000.0)
    assert hit.cos_incidence == pytest.approx(1.0)
    assert hit.next_mm == math.inf


def test_an_oblique_beam_travels_further_and_reports_its_incidence() -> None:
    d = np.array([1.0, 1.0, 0.0])
    hit = RangeScene((WALL,)).cast([1000.0, 0.0, 0.0], d)
    assert hit is not None
    assert hit.distance_mm == pytest.approx(4000.0 * math.sqrt(2.0))
    assert hit.cos_incidence == pytest.approx(1.0 / math.sqrt(2.0))


def test_a_surface_behind_or_parallel_to_the_beam_is_not_met() -> None:
    scene = RangeScene((WALL,))
    assert scene.cast([1000.0, 0.0, 0.0], [-1.0, 0.0, 0.0]) is None
    assert scene.cast([1000.0, 0.0, 0.0], [0.0, 1.0, 0.0]) is None


def test_a_board_is_met_only_within_its_radius_and_hides_the_wall_behind() -> None:
    board = Surface("board", (3000.0, 0.0, 0.0), (-1.0, 0.0, 0.0), radius_mm=200.0)
    scene = RangeScene((WALL, board))
    on = scene.cast([0.0, 100.0, 0.0], [1.0, 0.0, 0.0])
    off = scene.cast([0.0, 300.0, 0.0], [1.0, 0.0, 0.0])
    assert on is not None
    assert off is not None
    assert (scene.names()[on.surface], on.distance_mm, on.next_mm) == ("board", 3000.0, 5000.0)
    assert (scene.names()[off.surface], off.distance_mm) == ("wall", 5000.0)


@pytest.mark.parametrize(
    ("normal", "radius"), [((0.0, 0.0, 0.0), math.inf), ((1.0, 0.0, 0.0), 0.0)]
)
def test_a_degenerate_surface_is_refused_by_name(
    normal: tuple[float, float, float], radius: float
) -> None:
    with pytest.raises(ValueError, match="'bad'"):
        Surface("bad", (0.0, 0.0, 0.0), normal, radius)


def test_the_default_mount_looks_straight_down_at_the_floor() -> None:
    rig = Rig()
    origin, direction = beam_w(rig, 1234.0, 0.0, 0.0)
    np.testing.assert_allclose(direction, [0.0, 0.0, -1.0], atol=1e-12)
    hit = range_at(rig, RangeScene(hall_walls((-6000, 6000), (-4500, 4500))), 1234.0, 0.0, 0.0)
    assert hit is not None
    assert hit.distance_mm == pytest.approx(RUNWAY_HEIGHT_MM)
    assert origin[2] == pytest.approx(RUNWAY_HEIGHT_MM)


def test_looking_ahead_on_the_first_straight_reads_the_end_wall() -> None:
    rig = Rig()
    scene = RangeScene(hall_walls((-6000, 6000), (-4500, 4500)))
    near = range_at(rig, scene, 1000.0, 0.0, math.pi / 2)
    far = range_at(rig, scene, 1500.0, 0.0, math.pi / 2)
    assert near is not None
    assert far is not None
    assert scene.names()[near.surface] == "wall x+"
    # The first straight starts at x = -2000 heading +x: the wall at x = 6000 is 8 m - s away.
    assert near.distance_mm == pytest.approx(8000.0 - 1000.0, abs=1e-6)
    assert near.distance_mm - far.distance_mm == pytest.approx(500.0, abs=1e-6)
