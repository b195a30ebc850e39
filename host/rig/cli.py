"""`orbitar rig default` prints a rig file to start from; `orbitar rig check FILE` validates one."""

from __future__ import annotations

import argparse
import sys
from typing import Any

EXIT_BAD_FILE = 2
HEADER = (
    "Orbitar rig file: the paper's rig with nominal (drawing and datasheet) values.\n"
    "Edit the track, surfaces and workpiece for your rig; the commissioning commands\n"
    "(orbitar calibrate ..., orbitar survey ...) replace the calibrated blocks, each\n"
    "with its sigma and provenance. Point [rig] path in the daemon's config at this file."
)


def add_parser(subparsers: Any) -> None:
    """Register `orbitar rig`."""
    rig = subparsers.add_parser("rig", help="print or check a rig description file")
    sub = rig.add_subparsers(dest="rig_command", required=True)
    default = sub.add_parser("default", help="print the paper's rig as a rig file")
    default.set_defaults(handler=run_default)
    check = sub.add_parser("check", help="validate a rig file (exit 2 listing every problem)")
    check.add_argument("path")
    check.set_defaults(handler=run_check)


def run_default(args: argparse.Namespace) -> int:
    """Print the default rig file."""
    from host.rig import RigSpec, dumps_rig

    sys.stdout.write(dumps_rig(RigSpec(), HEADER))
    return 0


def run_check(args: argparse.Namespace) -> int:
    """Validate a rig file; 2 and every problem on stderr when it is wrong."""
    from host.rig import RigError, build_track, load_rig

    try:
        spec = load_rig(args.path)
    except RigError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        return EXIT_BAD_FILE
    kind = "closed" if build_track(spec.track).closed else "open"
    print(f"{args.path}: ok ({spec.name}, {spec.track.length_mm:.1f} mm track, {kind})")
    return 0
