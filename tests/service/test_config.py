"""Configuration: the defaults, every problem named, the default file loads; the rig is a file."""

from __future__ import annotations

from pathlib import Path

import pytest

from host.config import Config, default_config_text, load_config, loads_config
from host.config_fields import ConfigError


def problems(text: str) -> list[str]:
    """The problems ConfigError lists for `text`."""
    with pytest.raises(ConfigError) as exc:
        loads_config(text)
    return exc.value.problems


def test_defaults_point_at_the_built_in_rig() -> None:
    config = Config()
    assert config.rig.path == ""  # the paper's rig, nominal values (host.rig.RigSpec())
    assert config.camera.source == "sim"
    assert config.control.tcp_enabled is False


def test_default_file_loads_to_the_defaults(tmp_path: Path) -> None:
    text = default_config_text()
    assert text.count("\n# ") > 30  # commented, key by key
    assert "[rig]" in text
    path = tmp_path / "orbitar.toml"
    path.write_text(text)
    assert load_config(path) == Config()


def test_empty_file_is_the_default() -> None:
    assert loads_config("") == Config()


def test_every_problem_is_reported_with_key_value_and_reason() -> None:
    found = problems(
        """
[link]
kind = "pigeon"
baud = "fast"
node_id = 200
xbee_address = "12"
colour = "red"
[rig]
path = 5
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
    assert "rig.path = 5: expected str, got int" in text
    assert "control.socket_mode = 'rw'" in text
    assert "outputs.freed.destinations[1] = 'nowhere'" in text
    assert "nonsense: unknown key" in text
    assert len(found) == 9


def test_rig_sections_moved_to_the_rig_file() -> None:
    """[track], [head], [model], [rangefinder] and the intrinsics live in the rig file now."""
    found = problems("[track]\nheight_mm = 3000\n[camera]\nfx = 3000\n")
    assert any(p.startswith("track: unknown key") for p in found)
    assert any(p.startswith("camera.fx: unknown key") for p in found)


def test_cross_checks() -> None:
    assert problems("[control]\ntcp_enabled = true\n") == [
        "control.operator_token: required when control.tcp_enabled = true"
    ]


def test_camera_source_forms() -> None:
    assert loads_config("[camera]\nsource = 2\n").camera.source == 2
    url = "rtsp://127.0.0.1/x"
    assert loads_config(f'[camera]\nsource = "{url}"\n').camera.source == url
    assert any("device index must be >= 0" in p for p in problems("[camera]\nsource = -1\n"))


def test_toml_syntax_and_unreadable_file(tmp_path: Path) -> None:
    assert problems("[link\n")[0].startswith("TOML syntax")
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")
