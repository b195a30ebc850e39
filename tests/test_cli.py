"""The console entry point."""

from __future__ import annotations

import subprocess
import sys

import pytest

from host.cli import main


def test_version_prints_distribution_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("orbitar 0.")


def test_console_script_runs() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "host.cli", "--version"], capture_output=True, text=True, check=True
    )
    assert "orbitar" in out.stdout


def test_the_demo_commissions_by_default() -> None:
    """`orbitar demo` starts the host from the rig's description and commissions it (issue 11):
    handing the host the simulated truth is the opt-in `--tolerances off`."""
    from host.cli import build_parser

    args = build_parser("demo").parse_args(["demo"])
    assert args.tolerances == "on"
    assert args.commission == "auto"
    off = build_parser("demo").parse_args(["demo", "--tolerances", "off"])
    assert off.tolerances == "off"
