"""`orbitar daemon`: load the configuration, set up logging and run the Daemon."""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from host.config import Config, load_config
from host.config_fields import ConfigError
from host.service.lock import EXIT_ALREADY_RUNNING, AlreadyRunning
from host.service.logsetup import setup_logging
from host.service.preflight import preflight

if TYPE_CHECKING:
    from host.service.daemon import ControllerFactory, FrameLoopFactory

log = logging.getLogger(__name__)


def add_parser(subparsers: Any) -> None:
    """Register `orbitar daemon`."""
    parser = subparsers.add_parser("daemon", help="run the service (systemd starts this)")
    parser.add_argument("--config", help="TOML configuration file (default: built-in rig)")
    parser.add_argument("--log-level", help="override [log] level")
    parser.set_defaults(handler=run)


def run(
    args: argparse.Namespace,
    controller_factory: ControllerFactory | None = None,
    frame_loop_factory: FrameLoopFactory | None = None,
) -> int:
    """Run the daemon to completion; the process exit code (tests pass their own factories)."""
    try:
        config = load_config(args.config) if args.config else Config()
    except ConfigError as exc:
        print(f"orbitar daemon: {exc}", file=sys.stderr)
        return 2
    report = preflight(config, as_service=True)  # the same checks as `orbitar config check`
    if not report.ok:
        print(
            "orbitar daemon: " + "\n  ".join(["invalid configuration:", *report.errors]),
            file=sys.stderr,
        )
        return 2
    try:
        setup_logging(args.log_level or config.log.level)
    except ValueError as exc:
        print(f"orbitar daemon: {exc}", file=sys.stderr)
        return 2
    for note in report.notes:
        log.warning("configuration note", extra={"kv": {"note": note}})
    if controller_factory is None:
        from host.service import wiring  # the real link, camera and pose loop: only to run

        controller_factory = wiring.controller_factory
        frame_loop_factory = wiring.frame_loop_factory
    return asyncio.run(_serve(config, controller_factory, frame_loop_factory, args.config))


async def _serve(
    config: Config,
    controller_factory: ControllerFactory,
    frame_loop_factory: FrameLoopFactory | None,
    config_path: str | None,
) -> int:
    """Build the daemon on the running loop (the link objects bind to it) and run it."""
    from host.service.daemon import Daemon
    from host.service.wiring import WiringError

    try:
        daemon = Daemon(config, controller_factory, frame_loop_factory, config_path=config_path)
    except AlreadyRunning as exc:
        print(f"orbitar daemon: {exc}", file=sys.stderr)
        return EXIT_ALREADY_RUNNING
    except WiringError as exc:
        print(f"orbitar daemon: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the lock file's directory cannot be made or opened
        print(f"orbitar daemon: cannot start: {exc}", file=sys.stderr)
        return 1
    return await daemon.run()


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m host.service daemon …` without the full CLI."""
    parser = argparse.ArgumentParser(prog="orbitar")
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser(sub)
    args = parser.parse_args(argv)
    return int(args.handler(args))
