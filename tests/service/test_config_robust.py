"""Hostile config files: every bad value is named by key and reason, never a traceback."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import typing
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from host.cli import main as cli_main
from host.config import CONFIG_MAX_BYTES, Config, config_from_dict, load_config, loads_config
from host.config_fields import ConfigError
from host.geometry.head import M_CR_PAPER, orthonormalize_T
from host.rig import RigError, build_kinematics, loads_rig
from host.service.preflight import check_file, preflight

KEY = r'([A-Za-z0-9_-]+|"(?:[^"\\]|\\.)*"?)'  # bare or quoted (a long one is cut)
PROBLEM_RE = re.compile(rf"^{KEY}(\.{KEY}|\[\d+\])*( = .*)?: \S", re.DOTALL)


def problems(text: str) -> list[str]:
    """The problems ConfigError lists for `text`."""
    with pytest.raises(ConfigError) as exc:
        loads_config(text)
    return exc.value.problems


def config_check(tmp_path: Path, text: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """`orbitar config check` on `text`: exit code and what it printed on stderr."""
    path = tmp_path / "orbitar.toml"
    path.write_text(text)
    code = cli_main(["config", "check", str(path)])
    return code, capsys.readouterr().err


# ---- the files of the issue ---------------------------------------------------------------

ISSUE_FILES = {
    "scalar for a table": ("rig = 5\n", "rig = 5: expected a table"),
    "deep nesting": ("[link]\nurl = " + "[" * 3000 + "]" * 3000 + "\n", "link.url: "),
    "NUL in a path": (
        '[control]\nsocket_path = "/run/a\\u0000b"\n',
        "control.socket_path = '/run/a\\x00b': control character U+0000",
    ),
}


@pytest.mark.parametrize("name", ISSUE_FILES)
def test_config_check_names_the_key_of_each_bad_file(
    tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    text, expected = ISSUE_FILES[name]
    code, err = config_check(tmp_path, text, capsys)
    assert code == 2, err
    assert expected in err


def test_table_shaped_mistakes_are_named() -> None:
    assert problems("rig = [1, 2]\n") == ["rig = [1, 2]: expected a table"]
    assert problems("[outputs]\nfreed = 'on'\n") == ["outputs.freed = 'on': expected a table"]


def test_huge_numbers_and_values_are_named_and_cut() -> None:
    found = problems("[registration]\nhorizon_ms = " + "9" * 400 + "\n")
    assert found[0].startswith("registration.horizon_ms = 9999")
    assert "..." in found[0]  # the value is cut, the reason kept
    assert len(found[0]) < 200
    found = problems("[outputs.freed]\norigin_mm = [" + "9" * 400 + ", 0, 0]\n")
    assert found[0].endswith(": must be finite")
    assert problems("[link]\nbaud = 1" + "0" * 5000 + "\n")[0].startswith("TOML value: ")


def test_control_characters_are_refused_in_every_string() -> None:
    assert problems('[link]\nurl = "/dev/tty\\u001bUSB0"\n') == [
        "link.url = '/dev/tty\\x1bUSB0': control character U+001B at position 8"
    ]
    found = problems('[outputs.freed]\ndestinations = ["127.0.0.1\\u0000:4000"]\n')
    assert found[0].startswith("outputs.freed.destinations[0] = ")


def test_files_that_are_not_config_files_are_refused_without_reading_them(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # opening it must not wait for a writer
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config(fifo)
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config("/dev/zero")  # endless: read boundedly or not at all
    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * (CONFIG_MAX_BYTES + 1))
    with pytest.raises(ConfigError, match="larger than"):
        load_config(big)
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe[link]\n")
    with pytest.raises(ConfigError, match="cannot read: 'utf-8' codec"):
        load_config(binary)


# ---- rotations -----------------------------------------------------------------------------


def m_cr_toml(rows: Any, key: str = "head.m_cr") -> str:
    """A rig file setting the transform block `key` (rotations live in the rig file now)."""
    return f"[{key}]\nmatrix = {[[float(x) for x in r] for r in rows]}\n"


def rig_problems(text: str) -> list[str]:
    """The problems RigError lists for rig file text."""
    with pytest.raises(RigError) as exc:
        loads_rig(text)
    return exc.value.problems


BAD_ROTATIONS = {
    "zero rotation": (np.diag([0.0, 0.0, 0.0, 1.0]), "singular values 0/0/0"),
    "scale x10": (np.diag([10.0, 10.0, 10.0, 1.0]), "singular values 10/10/10"),
    "reflection": (np.diag([1.0, 1.0, -1.0, 1.0]), "a reflection (determinant -1.0000)"),
    "shear": (np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "off by"),
}


@pytest.mark.parametrize("name", BAD_ROTATIONS)
@pytest.mark.parametrize("key", ["head.m_cr", "rangefinder.mount"])
def test_a_matrix_that_is_no_rotation_is_refused_with_its_deviation(name: str, key: str) -> None:
    matrix, expected = BAD_ROTATIONS[name]
    found = rig_problems(m_cr_toml(matrix, key))
    assert len(found) == 1
    assert found[0].startswith(f"{key}.matrix = ")
    assert expected in found[0]


def test_printed_figures_are_accepted_and_orthonormalised_where_used() -> None:
    spec = loads_rig(m_cr_toml(M_CR_PAPER))  # eq. 14 as printed: 0.29 % off
    R = build_kinematics(spec).T_r_c[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3))


def test_the_geometry_refuses_to_orthonormalise_a_wrong_matrix() -> None:
    with pytest.raises(ValueError, match="reflection"):
        orthonormalize_T(np.diag([1.0, -1.0, 1.0, 1.0]))
    R = orthonormalize_T(M_CR_PAPER)[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3))
    assert np.linalg.det(R) == pytest.approx(1.0)


# ---- any shape at any key ------------------------------------------------------------------


def _keys(cls: type, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every table and key path of the schema, as TOML spells them."""
    out = []
    hints = typing.get_type_hints(cls)
    for fld in dataclasses.fields(cls):
        path = (*prefix, fld.metadata.get("key") or fld.name)
        out.append(path)
        hint = hints[fld.name]
        if dataclasses.is_dataclass(hint):
            out += _keys(typing.cast(type, hint), path)
    return out


KEYS = _keys(Config)
TOML_SCALARS = (
    st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**63 - 1)
    | st.floats()
    | st.text(max_size=12)
    | st.datetimes()
)
TOML_VALUES = st.recursive(
    TOML_SCALARS,
    lambda inner: (
        st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=6), inner, max_size=4)
    ),
    max_leaves=12,
)


def _nest(path: tuple[str, ...], value: Any) -> dict[str, Any]:
    table: dict[str, Any] = {path[-1]: value}
    for part in reversed(path[:-1]):
        table = {part: table}
    return table


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(path=st.sampled_from(KEYS), value=TOML_VALUES)
def test_any_value_at_any_key_is_named_never_raised(path: tuple[str, ...], value: Any) -> None:
    try:
        config = config_from_dict(_nest(path, value))
    except ConfigError as exc:
        found = exc.problems
    else:
        found = []
    if found:
        for problem in found:
            assert PROBLEM_RE.match(problem), problem
        assert any(p.startswith(path[0]) for p in found), found
        return
    report = preflight(config)  # a value that loads must get through every start check too
    for line in report.errors + report.notes:
        assert PROBLEM_RE.match(line), line


def toml_value(value: Any) -> str:
    """A value written as TOML (inline tables and arrays, JSON-style escaped strings)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)  # inf, -inf and nan are spelled as TOML spells them
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    return str(value.isoformat())  # a datetime


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(path=st.sampled_from(KEYS), value=TOML_VALUES)
def test_config_check_on_any_file_text_names_keys_and_never_raises(
    tmp_path_factory: pytest.TempPathFactory, path: tuple[str, ...], value: Any
) -> None:
    file = tmp_path_factory.mktemp("fuzz") / "orbitar.toml"
    file.write_text(f"{'.'.join(path)} = {toml_value(value)}\n", encoding="utf-8")
    _, report = check_file(file)  # what `orbitar config check` and the daemon's start run
    for line in report.errors + report.notes:
        assert PROBLEM_RE.match(line) or line.startswith("TOML syntax: "), line


def test_the_fuzz_reaches_every_section() -> None:
    sections = {p[0] for p in KEYS}
    assert {"link", "rig", "camera", "control", "outputs"} <= sections
    assert ("rig", "path") in KEYS
    assert ("outputs", "freed", "destinations") in KEYS
    assert len(KEYS) > 60


@pytest.mark.slow
@settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(path=st.sampled_from(KEYS), value=TOML_VALUES)
def test_any_value_at_any_key_soak(
    tmp_path_factory: pytest.TempPathFactory, path: tuple[str, ...], value: Any
) -> None:
    test_any_value_at_any_key_is_named_never_raised.hypothesis.inner_test(path, value)  # type: ignore[attr-defined]
    test_config_check_on_any_file_text_names_keys_and_never_raises.hypothesis.inner_test(  # type: ignore[attr-defined]
        tmp_path_factory, path, value
    )
