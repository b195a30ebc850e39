"""Configuration: defaults are the paper's rig, every problem is named, the default file loads."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from host.config import (
    PAPER_M_CR,
    Config,
    default_config_text,
    load_config,
    loads_config,
)
from host.config_fields import ConfigError


def problems(text: str) -> list[str]:
    """The problems ConfigError lists for `text`."""
    with pytest.raises(ConfigError) as exc:
        loads_config(text)
    return exc.value.problems


def test_defaults_are_the_papers_rig() -> None:
    config = Config()
    assert config.camera.fx == 3676.462
    assert (config.camera.width, config.camera.height, config.camera.fps) == (640, 480, 30.0)
    assert config.head.m_cr == PAPER_M_CR
    assert config.track.height_mm == 4000.0
    length = sum(
        s.length_mm if s.kind == "straight" else s.radius_mm * s.angle_rad
        for s in config.track.segments
    )
    assert length == pytest.approx(2 * (4000 + 1000) + 2 * math.pi * 1000)
    assert config.control.tcp_enabled is False


def test_default_file_loads_to_the_defaults(tmp_path: Path) -> None:
    text = default_config_text()
    assert text.count("\n# ") > 40  # commented, key by key
    path = tmp_path / "orbitar.toml"
    path.write_text(text)
    assert load_config(path) == Config()


def test_empty_file_is_the_default() -> None:
    assert loads_config("") == Config()


def test_degrees_become_radians() -> None:
    config = loads_config("[head]\npan_min_deg = -90\npan_max_deg = 90.0\n")
    assert config.head.pan_min_rad == pytest.approx(-math.pi / 2)
    assert config.head.pan_max_rad == pytest.approx(math.pi / 2)


def test_every_problem_is_reported_with_key_value_and_reason() -> None:
    found = problems(
        """
[link]
kind = "pigeon"
baud = "fast"
node_id = 200
xbee_address = "12"
colour = "red"
[camera]
fps = true
[control]
socket_mode = "rw"
[outputs.freed]
destinations = ["127.0.0.1:40000", "nowhere"]
[nonsense]
x = 1
"""
    )
    text = "\n".join(found)
    assert "link.kind = 'pigeon': must be one of 'serial', 'xbee', 'can'" in text
    assert "link.baud = 'fast': expected int, got str" in text
    assert "link.node_id = 200: out of range [1, 127]" in text
    assert "link.xbee_address = '12': expected 16 hex digits" in text
    assert "link.colour: unknown key" in text
    assert "camera.fps = True: expected float, got a boolean" in text
    assert "control.socket_mode = 'rw'" in text
    assert "outputs.freed.destinations[1] = 'nowhere'" in text
    assert "nonsense: unknown key" in text
    assert len(found) == 9


def test_custom_track_segments() -> None:
    config = loads_config(
        """
[track]
preset = "custom"
[[track.segments]]
kind = "straight"
length_mm = 2000
[[track.segments]]
kind = "arc"
radius_mm = 500
angle_deg = 180
"""
    )
    assert [s.kind for s in config.track.segments] == ["straight", "arc"]
    assert config.track.segments[1].angle_rad == pytest.approx(math.pi)


def test_segment_rules() -> None:
    found = problems(
        '[track]\npreset = "custom"\n[[track.segments]]\nkind = "arc"\nradius_mm = 0\n'
        '[[track.segments]]\nkind = "straight"\nlength = 5\n'
    )
    assert any("track.segments[0]: an arc needs" in p for p in found)
    assert any("track.segments[1].length: unknown key" in p for p in found)
    assert problems('[track]\npreset = "custom"\n') == [
        'track.segments: required when track.preset = "custom"'
    ]


def test_matrix_and_cross_checks() -> None:
    found = problems(
        "[head]\nm_cr = [[1, 0, 0], [0, 1, 0]]\ntilt_min_deg = 20\ntilt_max_deg = 10\n"
        "[control]\ntcp_enabled = true\n"
    )
    assert any(p.startswith("head.m_cr = ") and "4×4" in p for p in found)
    assert "head.tilt_min_deg: must be below head.tilt_max_deg" in found
    assert "control.operator_token: required when control.tcp_enabled = true" in found


def test_camera_source_forms() -> None:
    assert loads_config("[camera]\nsource = 2\n").camera.source == 2
    url = "rtsp://127.0.0.1/x"
    assert loads_config(f'[camera]\nsource = "{url}"\n').camera.source == url
    assert any("device index must be >= 0" in p for p in problems("[camera]\nsource = -1\n"))


def test_toml_syntax_and_unreadable_file(tmp_path: Path) -> None:
    assert problems("[link\n")[0].startswith("TOML syntax")
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")


def test_home_marks_and_workpiece_keys_load(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    path.write_text(
        "[track]\nhome_s_mm = 1250.5\nreference_marks_mm = [2000, 5000.25, 12000]\n"
        "[model]\nposition_mm = [3000, 1500, 0]\nyaw_deg = -45\n"
    )
    config = load_config(path)
    assert config.track.home_s_mm == 1250.5
    assert config.track.reference_marks_mm == (2000.0, 5000.25, 12000.0)
    assert config.model.position_mm == (3000.0, 1500.0, 0.0)
    assert config.model.yaw_rad == pytest.approx(-math.pi / 4)
    defaults = Config()
    assert (defaults.track.home_s_mm, defaults.track.reference_marks_mm) == (0.0, ())
    assert (defaults.model.position_mm, defaults.model.yaw_rad) == ((0.0, 0.0, 0.0), 0.0)
    text = default_config_text()
    for line in ("home_s_mm = 0.0", "reference_marks_mm = []", "position_mm = [0.0, 0.0, 0.0]"):
        assert line in text
    assert "\nyaw_deg = 0.0" in text.split("[model]")[1]


def test_home_marks_and_workpiece_problems_are_named() -> None:
    found = problems(
        '[track]\nreference_marks_mm = [5000, 2000, 2000, 99999]\nhome_s_mm = "near"\n'
        '[model]\nposition_mm = [1, 2]\nyaw_deg = "north"\n'
    )
    assert "track.reference_marks_mm[1] = 2000.0: must be above the previous mark 5000.0" in (
        " ".join(found)
    )
    assert any(p.startswith("track.reference_marks_mm[2] = 2000.0: must be above") for p in found)
    assert any(
        p.startswith("track.reference_marks_mm[3] = 99999.0: outside the track") for p in found
    )
    assert "track.home_s_mm = 'near': expected float, got str" in found
    assert "model.position_mm = [1, 2]: expected a list of 3 numbers" in found
    assert "model.yaw_deg = 'north': expected float, got str" in found
    assert len(found) == 6
    found = problems('[track]\nreference_marks_mm = [1000, "x", true]\nhome_s_mm = 1e9\n')
    assert "track.reference_marks_mm[1] = 'x': expected a number, got str" in found
    assert "track.reference_marks_mm[2] = True: expected a number, got bool" in found
    assert any(p.startswith("track.home_s_mm = 1000000000.0: out of range") for p in found)
    assert problems("[track]\nreference_marks_mm = 3000\n") == [
        "track.reference_marks_mm = 3000: expected a list"
    ]
    assert problems("[track]\nhome_s_mm = 17000\n") == [
        "track.home_s_mm = 17000.0: beyond the track's 16283.2 mm"
    ]


RANGEFINDER_TOML = """
[rangefinder]
noise_mm = 2.5
mount = [[1, 0, 0, 10], [0, 1, 0, 0], [0, 0, 1, -30], [0, 0, 0, 1]]
[[rangefinder.surfaces]]
name = "east wall"
point_mm = [6000, 0, 0]
normal = [-2, 0, 0]
[[rangefinder.surfaces]]
name = "target board"
point_mm = [0, 4000, 2500]
normal = [0, -1, 0]
radius_mm = 300
"""


def test_rangefinder_mount_and_surfaces_load() -> None:
    rf = loads_config(RANGEFINDER_TOML).rangefinder
    assert rf.noise_mm == 2.5
    assert rf.mount[0][3] == 10.0
    assert [s.name for s in rf.surfaces] == ["east wall", "target board"]
    assert rf.surfaces[0].radius_mm == 0.0  # unbounded
    assert rf.surfaces[1].point_mm == (0.0, 4000.0, 2500.0)
    assert Config().rangefinder.surfaces == ()
    assert "# [[rangefinder.surfaces]]" in default_config_text()


def test_rangefinder_problems_are_named() -> None:
    found = problems(
        "[rangefinder]\nnoise_mm = 0\n[[rangefinder.surfaces]]\npoint_mm = [1, 2]\n"
        "normal = [0, 0, 0]\nradius_mm = -5\ncolour = 'red'\n"
    )
    assert any(p.startswith("rangefinder.noise_mm = 0: out of range") for p in found)
    assert "rangefinder.surfaces[0].point_mm = [1, 2]: expected a list of 3 numbers" in found
    assert any(p.startswith("rangefinder.surfaces[0].radius_mm = -5: out of range") for p in found)
    assert any(p.startswith("rangefinder.surfaces[0].colour: unknown key") for p in found)
    assert "rangefinder.surfaces[0].normal = [0.0, 0.0, 0.0]: must be a non-zero vector" in found
    assert "rangefinder.surfaces[0].name: required" in found


def test_non_finite_vectors_are_refused_by_key() -> None:
    found = problems(
        "[model]\nposition_mm = [inf, 0, 0]\n"
        "[[rangefinder.surfaces]]\nname = 'w'\npoint_mm = [0, nan, 0]\nnormal = [1, 0, 0]\n"
    )
    assert "model.position_mm = [inf, 0, 0]: must be finite" in found
    assert "rangefinder.surfaces[0].point_mm = [0, nan, 0]: must be finite" in found
    found = problems(
        "[rangefinder]\nmount = [[1, 0, 0, inf], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"
    )
    assert len(found) == 1
    assert found[0].endswith(": must be finite")
    assert found[0].startswith("rangefinder.mount = ")


def test_a_normal_too_large_to_normalise_is_refused_by_key() -> None:
    found = problems("[[rangefinder.surfaces]]\nname = 'w'\nnormal = [1e200, 1e200, 0]\n")
    assert found == [
        "rangefinder.surfaces[0].normal = [1e+200, 1e+200, 0.0]: must be a non-zero vector"
    ]
