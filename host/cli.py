"""The `orbitar` command line: one entry point, subcommands added by each part of the system."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from importlib.metadata import PackageNotFoundError, version
from typing import Any

from host.bus import fleet
from host.commissioning import cli as commissioning_cli
from host.control import cli_commands
from host.demo import run as demo_run
from host.rig import cli as rig_cli


def _version() -> str:
    """Installed distribution version."""
    try:
        return version("orbitar")
    except PackageNotFoundError:
        return "0+unknown"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    parser = argparse.ArgumentParser(prog="orbitar", description=__doc__)
    parser.add_argument("--version", action="version", version=f"orbitar {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo_run.add_parser(sub)
    cli_commands.add_parsers(sub)
    commissioning_cli.add_parsers(sub)
    rig_cli.add_parser(sub)
    _add_sim_parser(sub)
    fleet.add_parser(sub)
    return parser


def _add_sim_parser(sub: Any) -> None:
    """`orbitar sim`: imported here, not at module import (hil_sim/cli.py defers the simulator)."""
    from hil_sim import cli as sim_cli

    sim_cli.add_parser(sub)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse arguments and run the chosen subcommand."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handler = getattr(args, "handler", None)
    if handler is not None:
        return int(handler(args))
    parser.print_help()
    return 0


if __name__ == "__main__":
    sys.exit(main())
