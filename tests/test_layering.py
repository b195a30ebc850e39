"""The layers of DESIGN.md hold: who may import whom, checked on every module's imports."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STDLIB = set(sys.stdlib_module_names)
# host code that may start the simulator: the demo and the `orbitar sim` registration only.
HOST_SIM_ENTRY_POINTS = ("host/demo/", "host/cli.py")


def _imports(path: Path) -> set[str]:
    """Top-level names of every import in a module (relative imports are not used here)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("path", _modules("protocol"), ids=lambda p: p.name)
def test_protocol_uses_the_standard_library_only(path: Path) -> None:
    for name in _imports(path):
        top = name.split(".")[0]
        assert top in STDLIB or top == "protocol", f"{path.name} imports {name}"


@pytest.mark.parametrize("path", _modules("firmware"), ids=lambda p: p.name)
def test_firmware_imports_only_protocol(path: Path) -> None:
    for name in _imports(path):
        top = name.split(".")[0]
        assert top in STDLIB or top in {"protocol", "firmware"}, f"{path.name} imports {name}"


@pytest.mark.parametrize("path", _modules("hil_sim"), ids=lambda p: p.name)
def test_simulator_takes_only_shared_math_from_host(path: Path) -> None:
    for name in _imports(path):
        if name.split(".")[0] == "host":  # the math, and the rig schema `sim --rig` reads
            assert name.startswith(("host.geometry", "host.rig")), f"{path.name} imports {name}"


@pytest.mark.parametrize("path", _modules("host"), ids=lambda p: str(p.relative_to(ROOT)))
def test_host_reaches_the_simulator_only_from_the_demo_and_the_sim_command(path: Path) -> None:
    rel = str(path.relative_to(ROOT))
    if rel.startswith(HOST_SIM_ENTRY_POINTS):
        return
    for name in _imports(path):
        assert name.split(".")[0] not in {"hil_sim", "firmware"}, f"{rel} imports {name}"
