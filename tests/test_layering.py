"""The layers of DESIGN.md hold: who may import whom, checked on every module's imports, and
what each `orbitar` subcommand loads, checked transitively in a fresh interpreter."""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from pathlib import Path

import pytest

from host.cli import COMMANDS, build_parser

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


# ---- what `orbitar CMD` loads, transitively ----------------------------------------------------

HEAVY = ("cv2", "matplotlib", "hil_sim", "firmware", "scipy", "numpy", "host.service.wiring")
OPERATOR_COMMANDS = ("status", "home", "stop", "estop", "clear", "move", "jog", "head", "watch")


def _modules_loaded_by(argv: list[str]) -> set[str]:
    """The modules in sys.modules after `orbitar ARGV --help`, run in a fresh interpreter."""
    code = (
        "import sys, host.cli\n"
        "try:\n"
        f"    host.cli.main({argv!r} + ['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print('\\n'.join(sorted(sys.modules)), file=sys.stderr)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return set(done.stderr.split())


def _heavy(modules: set[str]) -> list[str]:
    return sorted(m for m in modules if m.split(".")[0] in HEAVY or m in HEAVY)


@pytest.mark.parametrize("command", ["status", "move", "watch", "config"])
def test_operator_commands_load_no_vision_plotting_or_simulator(command: str) -> None:
    assert _heavy(_modules_loaded_by([command])) == []


def test_the_command_listing_imports_no_subcommand() -> None:
    loaded = _modules_loaded_by([])
    modules = {c.module for c in COMMANDS.values()}
    assert not loaded & modules
    assert _heavy(loaded) == []


def test_every_listed_command_is_registered_by_its_module_with_the_listed_help() -> None:
    for name, command in COMMANDS.items():
        parser = build_parser(name)
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        assert name in sub.choices, f"{command.module}.{command.register} does not add {name!r}"
        shown = {a.dest: a.help for a in sub._choices_actions}
        assert shown[name] == command.help, f"{name}: the table's help differs from the module's"
    assert set(OPERATOR_COMMANDS) <= set(COMMANDS)
