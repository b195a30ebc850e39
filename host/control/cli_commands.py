"""CLI subcommands that talk to the running daemon, plus config and systemd-unit.

`add_parsers(subparsers)` registers them all; each parser sets `handler`, so host/cli.py runs
`args.handler(args)` and exits with its return value: 0 on success, 1 when the daemon is not
running or refuses the request, 2 for a bad configuration file. Output goes through `emit`, so
a reader that stops early (`orbitar status | head -1`) ends the command quietly with 0.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import math
import os
import sys
from collections.abc import Callable
from typing import Any, TextIO

from host.config import Config, default_config_text
from host.control.client import ControlClient, ControlRequestError
from host.service.unit import DEFAULT_CONFIG, installed_executable, render_unit

SOCKET_ENV = "ORBITAR_SOCKET"
CLEAR_SCREEN = "\x1b[H\x1b[2J"

Handler = Callable[[argparse.Namespace], int]


def default_socket() -> str:
    """$ORBITAR_SOCKET, else the configured default path."""
    return os.environ.get(SOCKET_ENV) or Config().control.socket_path


def add_parsers(subparsers: Any) -> None:
    """Register every subcommand of this module."""
    simple = {
        "status": "show the daemon, link and controller state",
        "home": "home the trolley",
        "stop": "controlled stop",
        "estop": "emergency stop (latched until `clear`)",
        "clear": "clear a latched fault or e-stop",
    }
    for name, text in simple.items():
        _socket_parser(subparsers, name, text).set_defaults(handler=_op_handler(name))
    subparsers.choices["status"].set_defaults(handler=run_status)
    move = _socket_parser(subparsers, "move", "move the trolley to an arc length")
    move.add_argument("mm", type=float, help="target position along the track, mm")
    move.add_argument("--speed", type=float, help="cruise speed, mm/s")
    move.set_defaults(handler=run_move)
    jog = _socket_parser(subparsers, "jog", "move at constant velocity (0 stops)")
    jog.add_argument("mm_s", type=float, help="velocity, mm/s (negative: backwards)")
    jog.set_defaults(handler=run_jog)
    head = _socket_parser(subparsers, "head", "point the pan/tilt head")
    head.add_argument("pan_deg", type=float)
    head.add_argument("tilt_deg", type=float)
    head.set_defaults(handler=run_head)
    watch = _socket_parser(subparsers, "watch", "live view of pose, state and link")
    watch.add_argument("--count", type=int, help="exit after this many updates")
    watch.set_defaults(handler=run_watch)
    _add_offline_parsers(subparsers)


def _add_offline_parsers(subparsers: Any) -> None:
    """Commands that need no daemon."""
    config = subparsers.add_parser("config", help="check or print a configuration file")
    sub = config.add_subparsers(dest="config_command", required=True)
    check = sub.add_parser("check", help="validate a file (exit 2 listing every problem)")
    check.add_argument("path")
    check.set_defaults(handler=run_config_check)
    sub.add_parser("default", help="print the commented default file").set_defaults(
        handler=run_config_default
    )
    unit = subparsers.add_parser("systemd-unit", help="print the systemd service unit")
    unit.add_argument("--exec", dest="executable", help="path of the orbitar executable")
    unit.add_argument("--config", default=DEFAULT_CONFIG, help="config path for ExecStart")
    unit.set_defaults(handler=run_systemd_unit)


def _socket_parser(subparsers: Any, name: str, text: str) -> argparse.ArgumentParser:
    """A subcommand with the --socket and --json options."""
    parser: argparse.ArgumentParser = subparsers.add_parser(name, help=text)
    parser.add_argument("--socket", default=default_socket(), help="daemon control socket")
    parser.add_argument("--json", action="store_true", help="print the raw result as JSON")
    return parser


def _op_handler(op: str) -> Handler:
    """A handler sending `op` without arguments."""
    return lambda args: request(args, op)


def run_move(args: argparse.Namespace) -> int:
    """`orbitar move MM [--speed MM_S]`."""
    return request(args, "move", position_mm=args.mm, speed_mm_s=args.speed)


def run_jog(args: argparse.Namespace) -> int:
    """`orbitar jog MM_S`."""
    return request(args, "jog", velocity_mm_s=args.mm_s)


def run_head(args: argparse.Namespace) -> int:
    """`orbitar head PAN_DEG TILT_DEG` (degrees here, radians on the socket)."""
    pan, tilt = math.radians(args.pan_deg), math.radians(args.tilt_deg)
    return request(args, "head", pan_rad=pan, tilt_rad=tilt)


def request(args: argparse.Namespace, op: str, **op_args: Any) -> int:
    """Send one request and print its result; 1 with a clear message on any failure."""
    return _request(args, op, op_args)[0]


LINK_DOWN_EXIT = 3  # `orbitar status`: the daemon answers, but its controller data is stale


def run_status(args: argparse.Namespace) -> int:
    """`orbitar status`: as any request, but 3 while the controller link is down."""
    code, result = _request(args, "status", {})
    if code == 0 and isinstance(result, dict) and result.get("link_up") is False:
        return LINK_DOWN_EXIT
    return code


def _request(args: argparse.Namespace, op: str, op_args: dict[str, Any]) -> tuple[int, Any]:
    """Send one request and print its result: (exit code, result)."""
    try:
        result = asyncio.run(_one_request(args.socket, op, op_args))
    except (ConnectionError, FileNotFoundError) as exc:
        return _fail(f"daemon not running? cannot reach {args.socket}: {exc}"), None
    except ControlRequestError as exc:
        return _fail(f"{op} refused: {exc}"), None
    except TimeoutError:
        return _fail(f"{op}: no reply from the daemon"), None
    emit(_result_text(result, getattr(args, "json", False)))
    return 0, result


def _result_text(result: Any, as_json: bool) -> str:
    """A reply as the user sees it: JSON, an indented tree, or `ok`."""
    if as_json:
        return json.dumps(result, indent=2, default=str) + "\n"
    if result is None:
        return "ok\n"
    text = io.StringIO()
    _print_tree(result, text)
    return text.getvalue()


def emit(text: str, out: TextIO | None = None) -> bool:
    """Write and flush; False, quietly, when the reader has gone (a closed pipe)."""
    stream = sys.stdout if out is None else out
    try:
        stream.write(text)
        stream.flush()
    except BrokenPipeError:
        silence(stream)
        return False
    return True


def silence(stream: TextIO) -> None:
    """Point a stream whose reader has gone at /dev/null, so the exit-time flush cannot fail."""
    try:
        fd = stream.fileno()
    except (OSError, ValueError):  # no descriptor (io.UnsupportedOperation is both)
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


async def _one_request(path: str, op: str, op_args: dict[str, Any]) -> Any:
    """Connect, request, close."""
    async with await ControlClient.connect_unix(path) as client:
        return await client.request(op, **op_args)


def run_watch(args: argparse.Namespace) -> int:
    """`orbitar watch`: redraw on every pose/state/link event until Ctrl-C or --count."""
    try:
        return asyncio.run(_watch(args.socket, args.count, sys.stdout))
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # `orbitar watch | head`: the reader is done, so are we
        silence(sys.stdout)
        return 0
    except (ConnectionError, FileNotFoundError) as exc:
        return _fail(f"daemon not running? cannot reach {args.socket}: {exc}")
    except ControlRequestError as exc:
        return _fail(f"watch refused: {exc}")


async def _watch(path: str, count: int | None, out: TextIO) -> int:
    """Subscribe and render a small dashboard per event."""
    view: dict[str, Any] = {}
    async with await ControlClient.connect_unix(path) as client:
        view["status"] = await client.request("status")
        await client.request("subscribe", topics=["pose", "state", "link"])
        updates = 0
        while count is None or updates < count:
            event = await client.next_event(timeout_s=3600)
            view[event["topic"]] = event["data"]
            _render(view, out)
            updates += 1
    return 0


def _render(view: dict[str, Any], out: TextIO) -> None:
    """One frame of the watch view."""
    if out.isatty():
        out.write(CLEAR_SCREEN)
    state = view.get("state") or view.get("status", {}).get("controller", {})
    pose = view.get("pose") or view.get("status", {}).get("pose") or {}
    out.write(f"state: {state.get('state', '?')}  position_mm: {state.get('position_mm', '?')}\n")
    if pose:
        t = pose["T_w_c"]
        out.write(f"camera_mm: {t[0][3]:.1f} {t[1][3]:.1f} {t[2][3]:.1f}  s_mm: {pose['s_mm']}\n")
    if "link" in view:
        out.write("link: " + " ".join(f"{k}={v}" for k, v in view["link"].items()) + "\n")
    if "overflow" in view:
        out.write(f"dropped events: {view['overflow']['total']}\n")
    out.flush()


def run_config_check(args: argparse.Namespace) -> int:
    """`orbitar config check PATH`: the file, then every check the daemon's start makes."""
    from host.service.preflight import check_file

    _, report = check_file(args.path)
    for note in report.notes:
        print(f"{args.path}: note: {note}", file=sys.stderr)
    if not report.ok:
        problems = "\n  ".join(report.errors)
        print(f"{args.path}: invalid configuration:\n  {problems}", file=sys.stderr)
        return 2
    emit(f"{args.path}: ok\n")
    return 0


def run_config_default(args: argparse.Namespace) -> int:
    """`orbitar config default`."""
    emit(default_config_text())
    return 0


def run_systemd_unit(args: argparse.Namespace) -> int:
    """`orbitar systemd-unit [--exec PATH] [--config PATH]`."""
    try:
        executable = args.executable or installed_executable()
    except FileNotFoundError as exc:
        return _fail(str(exc))
    emit(render_unit(executable, args.config))
    return 0


def _print_tree(value: Any, out: TextIO, indent: str = "") -> None:
    """Nested maps as indented `key: value` lines."""
    if not isinstance(value, dict):
        out.write(f"{indent}{value}\n")
        return
    for key, item in value.items():
        if isinstance(item, dict):
            out.write(f"{indent}{key}:\n")
            _print_tree(item, out, indent + "  ")
        else:
            out.write(f"{indent}{key}: {item}\n")


def _fail(message: str) -> int:
    """Print to stderr and return the failure exit code."""
    print(f"orbitar: {message}", file=sys.stderr)
    return 1
