"""CLI subcommands that talk to the running daemon, plus config and systemd-unit.

`add_parsers(subparsers)` registers them all; each parser sets `handler`, so host/cli.py runs
`args.handler(args)` and exits with its return value: 0 on success, 1 when the daemon is not
running or refuses the request, 2 for a bad configuration file. Output goes through `emit`, so
a reader that stops early (`orbitar status | head -1`) ends the command quietly with 0.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import math
import os
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from host.config import Config, default_config_text
from host.control.cli_text import (
    controller_text,
    head_error_in_degrees,
    head_text,
    link_text,
    pose_text,
    status_text,
)
from host.control.client import ControlClient, ControlRequestError
from host.service.unit import DEFAULT_CONFIG, installed_executable, render_unit

SOCKET_ENV = "ORBITAR_SOCKET"
WATCH_RATE_HZ = 4.0  # a person reads a few redraws a second; more only flickers
WATCH_SILENT_S = 2.0  # no event for this long: say so (a dropped link sends nothing)
CLEAR_SCREEN = "\x1b[H\x1b[2J"

Handler = Callable[[argparse.Namespace], int]


def default_socket() -> str:
    """$ORBITAR_SOCKET, else the configured default path."""
    return os.environ.get(SOCKET_ENV) or Config().control.socket_path


def add_parsers(subparsers: Any) -> None:
    """Register every subcommand of this module."""
    status = _socket_parser(subparsers, "status", "show the daemon, link and controller state")
    status.set_defaults(handler=run_status)
    simple = {
        "stop": "controlled stop",
        "estop": "emergency stop (latched until `clear`)",
        "clear": "clear a latched fault or e-stop",
    }
    for name, text in simple.items():
        _socket_parser(subparsers, name, text).set_defaults(handler=_op_handler(name))
    jog = _socket_parser(subparsers, "jog", "move at constant velocity (0 stops)")
    jog.add_argument("mm_s", type=float, help="velocity, mm/s (negative: backwards)")
    jog.set_defaults(handler=run_jog)
    head = _socket_parser(subparsers, "head", "point the pan/tilt head")
    head.add_argument("pan_deg", type=float, help="pan, degrees")
    head.add_argument("tilt_deg", type=float, help="tilt, degrees")
    head.set_defaults(handler=run_head)
    watch = _socket_parser(subparsers, "watch", "live view of pose, state and link")
    watch.add_argument("--count", type=int, help="exit after this many updates")
    watch.add_argument(
        "--rate", type=float, default=WATCH_RATE_HZ, help="redraws per second at most (default 4)"
    )
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


def run_jog(args: argparse.Namespace) -> int:
    """`orbitar jog MM_S`."""
    return request(args, "jog", velocity_mm_s=args.mm_s)


def run_head(args: argparse.Namespace) -> int:
    """`orbitar head PAN_DEG TILT_DEG` (degrees here and in its errors, radians on the socket)."""
    pan, tilt = math.radians(args.pan_deg), math.radians(args.tilt_deg)
    return request(args, "head", pan_rad=pan, tilt_rad=tilt)


LINK_DOWN_EXIT = 3  # `orbitar status`: the daemon answers, but its controller data is stale


def run_status(args: argparse.Namespace) -> int:
    """`orbitar status`: readable (degrees, mm, faults by name, ages) or --json; 3 if link down."""
    try:
        status, link = asyncio.run(_status_and_link(args.socket))
    except (ConnectionError, FileNotFoundError) as exc:
        return _fail(f"daemon not running? cannot reach {args.socket}: {exc}")
    except ControlRequestError as exc:
        return _fail(f"status refused: {exc}")
    except TimeoutError:
        return _fail("status: no reply from the daemon")
    if args.json:
        emit(json.dumps(status, indent=2, default=str) + "\n")
    else:
        emit(status_text(status, link, time.monotonic_ns()))
    return LINK_DOWN_EXIT if status.get("link_up") is False else 0


async def _status_and_link(path: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The status op and, when the link has a controller, its statistics."""
    async with await ControlClient.connect_unix(path) as client:
        status = await client.request("status")
        try:
            link = await client.request("link_stats")
        except ControlRequestError:
            link = {}
    return status, link


def request(args: argparse.Namespace, op: str, **op_args: Any) -> int:
    """Send one request and print its result; 1 with a clear message on any failure."""
    return _request(args, op, op_args)[0]


def _request(args: argparse.Namespace, op: str, op_args: dict[str, Any]) -> tuple[int, Any]:
    """Send one request and print its result: (exit code, result)."""
    try:
        result = asyncio.run(_one_request(args.socket, op, op_args))
    except (ConnectionError, FileNotFoundError) as exc:
        return _fail(f"daemon not running? cannot reach {args.socket}: {exc}"), None
    except ControlRequestError as exc:
        text = head_error_in_degrees(str(exc)) if op == "head" else str(exc)
        return _fail(f"{op} refused: {exc.code}: {text}"), None
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
    """`orbitar watch`: a dashboard redrawn at most --rate times a second, or JSON lines."""
    try:
        return asyncio.run(_watch(args.socket, args.count, sys.stdout, args.json, args.rate))
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # `orbitar watch | head`: the reader is done, so are we
        silence(sys.stdout)
        return 0
    except (ConnectionError, FileNotFoundError) as exc:
        return _fail(f"daemon not running? cannot reach {args.socket}: {exc}")
    except ControlRequestError as exc:
        return _fail(f"watch refused: {exc}")


async def _watch(
    path: str, count: int | None, out: TextIO, as_json: bool, rate_hz: float = WATCH_RATE_HZ
) -> int:
    """Subscribe; JSON lines per event, or a dashboard that also says when updates stop."""
    period_s = 1.0 / max(rate_hz, 0.1)
    view: dict[str, Any] = {}
    async with await ControlClient.connect_unix(path) as client:
        view["status"] = await client.request("status")
        with contextlib.suppress(ControlRequestError):  # the first link figures, before events
            link = await client.request("link_stats")
            view["link"] = {"up": view["status"].get("link_up", False), **link}
        await client.request("subscribe", topics=["pose", "state", "link"])
        updates = 0
        last_event_s = last_draw_s = time.monotonic()
        while count is None or updates < count:
            try:
                event = await client.next_event(timeout_s=period_s)
            except TimeoutError:
                event = None
            except ConnectionError:
                out.write("the daemon closed the connection (stopped or restarted)\n")
                out.flush()
                return 1
            now = time.monotonic()
            if event is not None:
                last_event_s = now
                view[event["topic"]] = event["data"]
                if as_json:
                    emit(json.dumps(event, default=str) + "\n", out)
                    updates += 1
                    continue
            view["silent_s"] = now - last_event_s
            if not as_json and now - last_draw_s >= period_s:
                _render(view, out)
                last_draw_s = now
                updates += 1
    return 0


def _render(view: dict[str, Any], out: TextIO) -> None:
    """One frame of the watch view."""
    status = view.get("status", {})
    controller = {**status.get("controller", {}), **view.get("state", {})}
    link = view.get("link", {})
    up = link.get("up", link.get("state") == "up") if link else status.get("link_up", False)
    text = CLEAR_SCREEN if out.isatty() else ""
    text += link_text(bool(up), link)
    text += controller_text(controller, link)
    text += head_text(controller)
    text += pose_text(view.get("pose") or status.get("pose"), time.monotonic_ns())
    silent = view.get("silent_s", 0.0)
    if silent > WATCH_SILENT_S:
        text += f"NO UPDATES for {silent:.1f} s: the link or the daemon is silent\n"
    if "overflow" in view:
        text += f"dropped events: {view['overflow']['total']}\n"
    if not out.isatty():
        text += "\n"
    emit(text, out)


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
