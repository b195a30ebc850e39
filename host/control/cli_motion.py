"""`orbitar home` and `orbitar move`: start the motion, then follow it to its end.

The daemon accepts a motion at once and the trolley takes seconds to minutes, so a command that
returned "ok" at once let the next one (`orbitar survey home`, another move) start while the
trolley was still homing, and be refused. These wait by default: they follow the status until
the controller is READY where it was sent (homed, for `home`), show the position while it
moves on a terminal, and exit 1 naming the state when it latches instead (FAULT, ESTOP) or
the link drops. Ctrl-C while waiting stops the trolley: the person who started the motion
and interrupts its command wants it to stop. `--no-wait` returns once the daemon accepted.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from host.control.cli_commands import _fail, _result_text, _socket_parser, emit
from host.control.cli_text import faults_text, fmt
from host.control.client import ControlClient, ControlRequestError

POLL_S = 0.1  # status polls while waiting: the position shown is at most this old
SETTLE_S = 1.0  # READY at the target without a move seen: the motion ended before the first poll
AT_TARGET_MM = 1.0  # where a finished move reads its encoder, within a few steps of the target
LATCHED = ("FAULT", "ESTOP")
CLEAR_LINE = "\r\x1b[2K"

Done = Callable[[dict[str, Any]], bool]


def add_parsers(subparsers: Any) -> None:
    """`home` and `move`, each with --no-wait."""
    home = _socket_parser(subparsers, "home", "home the trolley (waits until it is homed)")
    home.set_defaults(handler=run_home)
    move = _socket_parser(subparsers, "move", "move the trolley to an arc length (waits there)")
    move.add_argument("mm", type=float, help="target position along the track, mm")
    move.add_argument("--speed", type=float, help="cruise speed, mm/s")
    move.set_defaults(handler=run_move)
    for parser in (home, move):
        parser.add_argument(
            "--no-wait", action="store_true", help="return once the daemon accepted the motion"
        )


def run_home(args: argparse.Namespace) -> int:
    """`orbitar home [--no-wait]`."""
    return _run(args, "home", {}, lambda c: bool(c.get("homed")) and c.get("state") == "READY")


def run_move(args: argparse.Namespace) -> int:
    """`orbitar move MM [--speed MM_S] [--no-wait]`."""

    def there(c: dict[str, Any]) -> bool:
        position = c.get("position_mm")
        return position is not None and abs(float(position) - args.mm) <= AT_TARGET_MM

    return _run(args, "move", {"position_mm": args.mm, "speed_mm_s": args.speed}, there)


def _run(args: argparse.Namespace, op: str, op_args: dict[str, Any], at_end: Done) -> int:
    try:
        return asyncio.run(_command(args, op, op_args, at_end, sys.stdout))
    except KeyboardInterrupt:
        stopped = _stop(args.socket)
        return _fail(f"{op} interrupted: {'trolley stopped' if stopped else 'STOP not confirmed'}")
    except (ConnectionError, FileNotFoundError) as exc:
        return _fail(f"daemon not running? cannot reach {args.socket}: {exc}")
    except ControlRequestError as exc:
        return _fail(f"{op} refused: {exc.code}: {exc}")
    except TimeoutError:
        return _fail(f"{op}: no reply from the daemon")
    except MotionError as exc:
        return _fail(f"{op}: {exc}")


class MotionError(Exception):
    """The motion ended somewhere other than where it was sent."""


async def _command(
    args: argparse.Namespace, op: str, op_args: dict[str, Any], at_end: Done, out: TextIO
) -> int:
    async with await ControlClient.connect_unix(args.socket) as client:
        result = await client.request(op, **{k: v for k, v in op_args.items() if v is not None})
        if args.no_wait:
            emit(_result_text(result, args.json), out)
            return 0
        ctrl = await follow(client, at_end, out if out.isatty() and not args.json else None)
    if args.json:
        emit(_result_text(ctrl, True), out)
    else:
        emit(f"{op} done: {where(ctrl)}\n", out)
    return 0


async def follow(client: ControlClient, at_end: Done, tty: TextIO | None) -> dict[str, Any]:
    """Poll the status until the controller is READY and `at_end` holds; the last controller
    status. A motion that finished before the first poll is READY at its end within SETTLE_S;
    a latched controller or a dropped link raises MotionError."""
    started = time.monotonic()
    moved = False
    while True:
        status = await client.request("status")
        ctrl = status.get("controller") or {}
        state = str(ctrl.get("state"))
        if not status.get("link_up", False):
            raise MotionError("the controller's link is down: where the trolley is is unknown")
        if state in LATCHED:
            raise MotionError(f"the controller latched: {where(ctrl)}")
        moved = moved or state not in ("READY", "IDLE")
        if state == "READY" and at_end(ctrl) and (moved or time.monotonic() - started > POLL_S):
            _clear(tty)
            return dict(ctrl)
        if state in ("READY", "IDLE") and (moved or time.monotonic() - started > SETTLE_S):
            _clear(tty)
            raise MotionError(f"it ended elsewhere: {where(ctrl)}")
        if tty is not None:
            tty.write(f"{CLEAR_LINE}{where(ctrl)}")
            tty.flush()
        await asyncio.sleep(POLL_S)


def where(ctrl: dict[str, Any]) -> str:
    """`READY · no faults · position 600.0 mm · homed`."""
    state, faults = str(ctrl.get("state", "UNKNOWN")), faults_text(ctrl)
    position = f"position {fmt(ctrl.get('position_mm'), 1, ' mm')}"
    return " · ".join((state, faults, position, "homed" if ctrl.get("homed") else "NOT HOMED"))


def _clear(tty: TextIO | None) -> None:
    if tty is not None:
        tty.write(CLEAR_LINE)
        tty.flush()


def _stop(path: str) -> bool:
    """STOP after Ctrl-C: True once the daemon took it."""
    try:
        asyncio.run(_stop_request(path))
    except (OSError, ControlRequestError, TimeoutError):
        return False
    return True


async def _stop_request(path: str) -> None:
    async with await ControlClient.connect_unix(path) as client:
        await client.request("stop")
