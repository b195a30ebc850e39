"""`python -m host.control COMMAND …`: the control CLI before host/cli.py wires it in."""

import argparse
import sys

from host.control.cli_commands import add_parsers


def main() -> int:
    """Parse and dispatch."""
    parser = argparse.ArgumentParser(prog="orbitar")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args()
    return int(args.handler(args))


sys.exit(main())
