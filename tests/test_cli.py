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
