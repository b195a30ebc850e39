"""The `orbitar` command line: one entry point, subcommands loaded lazily from a name table.

`COMMANDS` maps each subcommand to the module that registers it (as python-can's BACKENDS maps
an interface name to its module): only the module of the command being run is imported, so
`orbitar status` never loads OpenCV, matplotlib, the simulator or the daemon. `orbitar --help`
lists the table without importing any of them. A part of the system adds its commands with a
row here and a `register(subparsers)` function in its module.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Command:
    """Where a subcommand lives: `module.register(subparsers)` adds it (and its siblings)."""

    module: str
    register: str
    help: str


_OPS = "host.control.cli_commands"
_MOTION = "host.control.cli_motion"  # the two that wait for the trolley
COMMANDS: dict[str, Command] = {
    "status": Command(_OPS, "add_parsers", "show the daemon, link and controller state"),
    "home": Command(_MOTION, "add_parsers", "home the trolley (waits until it is homed)"),
    "stop": Command(_OPS, "add_parsers", "controlled stop"),
    "estop": Command(_OPS, "add_parsers", "emergency stop (latched until `clear`)"),
    "clear": Command(_OPS, "add_parsers", "clear a latched fault or e-stop"),
    "move": Command(_MOTION, "add_parsers", "move the trolley to an arc length (waits there)"),
    "jog": Command(_OPS, "add_parsers", "move at constant velocity (0 stops)"),
    "head": Command(_OPS, "add_parsers", "point the pan/tilt head"),
    "watch": Command(_OPS, "add_parsers", "live view of pose, state and link"),
    "config": Command(_OPS, "add_parsers", "check or print a configuration file"),
    "systemd-unit": Command(_OPS, "add_parsers", "print the systemd service unit"),
    "daemon": Command("host.service.main", "add_parser", "run the service (systemd starts this)"),
    "replay": Command(
        "host.service.replay_registration",
        "add_parser",
        "re-run the link, clock sync and registration on a recording",
    ),
    "demo": Command(
        "host.demo.run",
        "add_parser",
        "run the paper's experiments on the built-in simulator, write a report",
    ),
    "sim": Command(
        "hil_sim.cli",
        "add_parser",
        "run the emulated controller behind a pty, TCP, XBee or CAN link",
    ),
    "install-service": Command("host.service.install", "add_parser", "set up the systemd service"),
    "fleet": Command(
        "host.bus.fleet", "add_parser", "list the rigs on the bus and their state, live"
    ),
    "rig": Command("host.rig.cli", "add_parser", "print or check a rig description file"),
    "calibrate": Command(
        "host.commissioning.cli",
        "add_parsers",
        "commissioning: calibrate the rig through the daemon",
    ),
    "conformance": Command(
        "host.conformance.run", "add_parser", "check a controller against PROTOCOL.md over its wire"
    ),
    "survey": Command(
        "host.commissioning.cli",
        "add_parsers",
        "commissioning: survey with the rangefinder (or the camera)",
    ),
}


def _version() -> str:
    """Installed distribution version."""
    from importlib.metadata import PackageNotFoundError, version  # 20 ms: only when asked

    try:
        return version("orbitar")
    except PackageNotFoundError:
        return "0+unknown"


class _VersionAction(argparse.Action):
    """`--version`, looked up only when given."""

    def __init__(self, option_strings: list[str], dest: str, **kwargs: object) -> None:
        super().__init__(option_strings, dest, nargs=0, help="print the version and exit")

    def __call__(self, parser: argparse.ArgumentParser, *args: object) -> None:
        print(f"orbitar {_version()}")
        parser.exit()


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser for `command` (its module imported), or the listing of every command."""
    parser = argparse.ArgumentParser(prog="orbitar", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    entry = COMMANDS.get(command) if command is not None else None
    if entry is not None:
        register = getattr(importlib.import_module(entry.module), entry.register)
        register(sub)
        return parser
    for name, listed in COMMANDS.items():  # names and help only: nothing imported
        sub.add_parser(name, help=listed.help, add_help=False)
    return parser


def _command_of(argv: Sequence[str]) -> str | None:
    """The subcommand named on the line (top-level options take no values)."""
    return next((arg for arg in argv if not arg.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    """Parse arguments and run the chosen subcommand."""
    args_in = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_command_of(args_in))
    args = parser.parse_args(args_in)
    handler = getattr(args, "handler", None)
    if handler is not None:
        return int(handler(args))
    parser.print_help()
    return 0


if __name__ == "__main__":
    sys.exit(main())
