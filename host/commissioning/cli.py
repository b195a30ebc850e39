"""`orbitar calibrate ...` and `orbitar survey ...`: commissioning runs on the running daemon.

Each subcommand sends its request over the control socket, redraws the run's progress (views
and the X/Y/size/skew coverage bars) until it ends, then prints the verdict, the short table
and the report's path. Exit 0 when the run passed, 1 when it failed, could not start or was
interrupted (Ctrl-C cancels the run in the daemon; nothing is written).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
from typing import Any, TextIO

from host.calibration.board import BoardSpec
from host.commissioning import coverage
from host.commissioning.client import RunFailedError, run_op
from host.control.cli_commands import default_socket, emit
from host.control.client import ControlClient, ControlRequestError

CLEAR_LINE = "\x1b[2K\r"


def add_parsers(subparsers: Any) -> None:
    """Register `calibrate` (and its subcommands)."""
    cal = subparsers.add_parser(
        "calibrate", help="commissioning: calibrate the rig through the daemon"
    )
    sub = cal.add_subparsers(dest="calibrate_command", required=True)
    intr = _common(sub.add_parser("intrinsics", help="camera intrinsics from a board in view"))
    _board_args(intr)
    intr.add_argument("--full-distortion", action="store_true", help="also solve p1, p2, k3")
    intr.add_argument("--max-rms", type=float, help="pass threshold, px (default 0.5)")
    intr.add_argument("--min-views", type=int, help="views needed (default 10)")
    intr.set_defaults(handler=run_intrinsics)
    head = _common(
        sub.add_parser("head", help="M_cr and the track placement from a surveyed board")
    )
    _board_args(head, centre=False)
    _pose_args(head)
    head.set_defaults(handler=lambda a: run_posed(a, "calibrate_head"))
    check = _common(
        sub.add_parser("check", help="acceptance test: predicted against measured corners")
    )
    _board_args(check, centre=False)
    _pose_args(check)
    check.add_argument("--max-rms", type=float, help="pass threshold, px (default 1.0)")
    check.set_defaults(handler=lambda a: run_posed(a, "calibrate_check"))
    lat = _common(sub.add_parser("latency", help="frame stamp to exposure offset, from passes"))
    _board_args(lat, centre=False)
    _pose_args(lat)
    lat.add_argument("--station", type=float, required=True, help="arc length facing the board, mm")
    lat.add_argument("--span", type=float, default=200.0, help="pass length, mm (default 200)")
    lat.add_argument("--passes", type=int, default=6, help="passes back and forth (default 6)")
    lat.set_defaults(handler=lambda a: run_posed(a, "calibrate_latency"))
    rf = _common(
        sub.add_parser("rangefinder", help="the rangefinder's mount from readings on the hall")
    )
    rf.add_argument("--stations", type=float, nargs="+", metavar="S_MM",
                    help="arc lengths to range from (default: 4 along the travel)")  # fmt: skip
    rf.add_argument("--pans", type=int, default=8, help="head pans per station and tilt")
    rf.add_argument("--tilts-deg", type=float, nargs="+", metavar="DEG",
                    help="head tilts (default: 3 between the floor and the horizon)")  # fmt: skip
    rf.add_argument("--aims", metavar="FILE", help="JSON [[s_mm, pan_rad, tilt_rad], ...] poses")
    rf.add_argument("--samples", type=int, default=5, help="readings averaged per pose")
    rf.add_argument("--max-rms", type=float, help="pass threshold, mm (default 2.0)")
    rf.set_defaults(handler=run_calibrate_rangefinder)
    survey = subparsers.add_parser(
        "survey", help="commissioning: survey with the rangefinder (or the camera)"
    )
    ssub = survey.add_subparsers(dest="survey_command", required=True)
    wp = _common(
        ssub.add_parser("workpiece", help="the workpiece frame from its feature points"), False
    )
    method_help = (
        "rangefinder: the beam on each feature (--aims); camera: targets stuck on the "
        "features, triangulated from --stations (needs --model-points)"
    )
    wp.add_argument(
        "--method", choices=("rangefinder", "camera"), default="rangefinder", help=method_help
    )
    aims_help = "rangefinder: JSON [[s_mm, pan_rad, tilt_rad], ...], the beam on each feature"
    wp.add_argument("--aims", metavar="FILE", help=aims_help)
    model_help = (
        "the features in the model's frame, mm: a JSON [[x, y, z], ...], the model's parts "
        "sidecar (its P1..Pn), or the model's name (builtin:manipulator, or its file: the "
        "sidecar beside it)"
    )
    wp.add_argument("--model-points", metavar="FILE", help=model_help)
    stations_help = (
        "camera: arc lengths to view the targets from (default: where the trolley is; "
        "give 2-3 around the workpiece, for rays that cross)"
    )
    wp.add_argument("--stations", type=float, nargs="+", metavar="S_MM", help=stations_help)
    wp.add_argument("--samples", type=int, default=10, help="readings averaged per point")
    wp.set_defaults(handler=run_survey_workpiece)
    home = _common(
        ssub.add_parser("home", help="the controller's zero on the track, from a wall"), False
    )
    home.add_argument("pan_deg", type=float, help="head pan putting the beam on an end wall")
    home.add_argument("tilt_deg", type=float, help="head tilt")
    home.add_argument("--samples", type=int, default=20, help="readings averaged")
    home.add_argument("--rig-sigma", type=float, metavar="MM",
                      help="how well the rig file places the beam's origin along the beam "
                      "(default 0: a calibrated head; before `calibrate head`, the placement's "
                      "and the mount's σ combined, e.g. 5.8)")  # fmt: skip
    home.add_argument("--max-sigma", type=float, metavar="MM",
                      help="pass threshold, mm (default 2; 10 for a first zero before the head "
                      "is calibrated)")  # fmt: skip
    home.set_defaults(handler=run_survey_home)
    marks = _common(
        ssub.add_parser("marks", help="each reference mark's arc length, from a wall"), False
    )
    marks.add_argument("--samples", type=int, default=20, help="readings averaged per mark")
    marks.add_argument("--cross-speed", type=float, help="speed across each mark, mm/s (100)")
    marks.add_argument("--aim-deg", type=float, nargs=2, metavar=("PAN", "TILT"),
                       help="one head aim for every mark (default: chosen per mark)")  # fmt: skip
    marks.add_argument("--max-sigma", type=float, help="pass threshold per mark, mm (default 2)")
    marks.add_argument("--marks", type=int, nargs="+", metavar="INDEX",
                       help="only these of the listed marks (0-based; default all)")  # fmt: skip
    marks.set_defaults(handler=run_survey_marks)
    track = _common(
        ssub.add_parser(
            "track", help="the first corner's place along the track and the arcs' radius"
        )
    )
    track.add_argument("--stations", type=float, nargs="+", metavar="S_MM",
                       help="arc lengths to range from (default: one on the first straight, "
                       "two through the first arc, one past it)")  # fmt: skip
    track.add_argument("--pans", type=int, default=8, help="head pans per station")
    track.add_argument("--samples", type=int, default=5, help="readings averaged per pose")
    track.add_argument("--max-corner-sigma", type=float, metavar="MM",
                       help="pass threshold on the corner's σ, mm (default 1.5)")  # fmt: skip
    track.add_argument("--max-radius-sigma", type=float, metavar="MM",
                       help="pass threshold on the radius' σ, mm (default 1.5)")  # fmt: skip
    track.add_argument("--max-rms", type=float, help="pass threshold, mm (default 2.0)")
    track.set_defaults(handler=run_survey_track)


def _common(p: argparse.ArgumentParser, speed: bool = True) -> argparse.ArgumentParser:
    p.add_argument("--socket", default=default_socket(), help="daemon control socket")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--no-write", action="store_true", help="report only, leave the rig file alone")
    if speed:  # the surveys move at the daemon's own speeds
        p.add_argument("--speed", type=float, help="trolley speed between stations, mm/s")
    return p


def _pose_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--board-pose", required=True, metavar="FILE",
                   help="the board's surveyed world pose: a JSON 4×4 matrix (mm)")  # fmt: skip
    p.add_argument("--board-sigma-mm", type=float, default=1.0, help="survey σ of its position")
    p.add_argument("--board-sigma-mrad", type=float, default=1.0, help="survey σ of its attitude")


def _board_args(p: argparse.ArgumentParser, centre: bool = True) -> None:
    base = BoardSpec()
    where = "where the board's centre is in the world, mm (a tape measure is enough)"
    if centre:
        xyz = ("X", "Y", "Z")
        p.add_argument(
            "--board-centre", type=float, nargs=3, required=True, metavar=xyz, help=where
        )
    p.add_argument("--stations", type=float, nargs="+", metavar="S_MM",
                   help="arc lengths to view from (default: where the trolley is)")  # fmt: skip
    p.add_argument(
        "--squares", default=f"{base.squares_x}x{base.squares_y}", help="board squares, COLSxROWS"
    )
    p.add_argument("--square-mm", type=float, default=base.square_mm, help="square edge, mm")
    p.add_argument("--marker-mm", type=float, default=base.marker_mm, help="marker edge, mm")
    p.add_argument("--dictionary", default=base.dictionary, help="ArUco dictionary")


def board_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The board map of the request (ValueError names a bad --squares)."""
    try:
        cols, rows = (int(x) for x in args.squares.lower().split("x"))
    except ValueError as exc:
        raise ValueError(f"--squares {args.squares!r}: expected COLSxROWS, e.g. 9x7") from exc
    spec = BoardSpec(cols, rows, args.square_mm, args.marker_mm, args.dictionary)
    return spec.to_dict()


def run_intrinsics(args: argparse.Namespace) -> int:
    """`orbitar calibrate intrinsics`."""
    try:
        req: dict[str, Any] = {
            "board_centre_mm": list(args.board_centre),
            "board": board_from_args(args),
        }
    except ValueError as exc:
        return _fail(str(exc))
    if args.stations:
        req["stations_mm"] = list(args.stations)
    for key, value in (
        ("max_rms_px", args.max_rms),
        ("min_views", args.min_views),
        ("speed_mm_s", args.speed),
    ):
        if value is not None:
            req[key] = value
    req["write"] = not args.no_write
    req["full_distortion"] = args.full_distortion
    return follow(args, "calibrate_intrinsics", req)


def run_posed(args: argparse.Namespace, op: str) -> int:
    """`orbitar calibrate head` / `check`: the board pose from its survey file."""
    try:
        with open(args.board_pose, encoding="utf-8") as f:
            pose = json.load(f)
        req: dict[str, Any] = {"board_pose": pose, "board": board_from_args(args)}
    except (OSError, ValueError) as exc:
        return _fail(f"--board-pose {args.board_pose}: {exc}")
    req["board_sigma_mm"] = args.board_sigma_mm
    req["board_sigma_rad"] = args.board_sigma_mrad / 1000.0
    if args.stations and op != "calibrate_latency":
        req["stations_mm"] = list(args.stations)
    if args.speed is not None:
        req["speed_mm_s"] = args.speed
    if op == "calibrate_latency":
        req.update(station_mm=args.station, span_mm=args.span, passes=args.passes)
    if getattr(args, "max_rms", None) is not None:
        req["max_rms_px"] = args.max_rms
    req["write"] = not args.no_write
    return follow(args, op, req)


def run_survey_workpiece(args: argparse.Namespace) -> int:
    """`orbitar survey workpiece --aims FILE [--model-points FILE]`, or `--method camera
    --model-points FILE [--stations S_MM ...]`."""
    camera = args.method == "camera"
    if camera and not args.model_points:
        return _fail("--method camera needs --model-points: where the targets sit in the model")
    if not camera and not args.aims:
        return _fail("--aims FILE is needed (or --method camera with --model-points)")
    req: dict[str, Any] = {"method": args.method}
    try:
        if camera:
            if args.stations:
                req["stations_mm"] = list(args.stations)
        else:
            req.update(aims=_json(args.aims), samples=args.samples)
        if args.model_points:
            req["model_points_mm"] = model_points(args.model_points)
    except (OSError, ValueError) as exc:
        return _fail(str(exc))
    req["write"] = not args.no_write
    return follow(args, "survey_workpiece", req)


def model_points(where: str) -> Any:
    """`--model-points`: a JSON list of points, a parts sidecar, or a model (its sidecar)."""
    from host.station.parts import PartsError, load_parts, parse_parts, sidecar_path

    try:
        if where.startswith("builtin:") or not where.endswith(".json"):
            path = sidecar_path(where)
            parts = load_parts(path, required=True)
        else:
            table = _json(where)
            if isinstance(table, list):
                return table
            parts = parse_parts(table)
    except PartsError as exc:
        raise ValueError(f"--model-points {where}: {exc}") from exc
    if not parts.points:
        raise ValueError(f"--model-points {where}: the sidecar lists no feature points")
    return [list(p.position_mm) for p in parts.points]


def run_survey_home(args: argparse.Namespace) -> int:
    """`orbitar survey home PAN_DEG TILT_DEG` (degrees here, radians on the socket)."""
    req: dict[str, Any] = {
        "pan_rad": math.radians(args.pan_deg), "tilt_rad": math.radians(args.tilt_deg),
    }  # fmt: skip
    req.update(samples=args.samples, write=not args.no_write)
    for key, value in (("rig_sigma_mm", args.rig_sigma), ("max_sigma_mm", args.max_sigma)):
        if value is not None:
            req[key] = value
    return follow(args, "survey_home", req)


def run_survey_marks(args: argparse.Namespace) -> int:
    """`orbitar survey marks`."""
    req: dict[str, Any] = {"samples": args.samples, "write": not args.no_write}
    if args.aim_deg:
        req["aim_rad"] = [math.radians(a) for a in args.aim_deg]
    if args.marks:
        req["marks"] = list(args.marks)
    for key, value in (("cross_speed_mm_s", args.cross_speed), ("max_sigma_mm", args.max_sigma)):
        if value is not None:
            req[key] = value
    return follow(args, "survey_marks", req)


def run_survey_track(args: argparse.Namespace) -> int:
    """`orbitar survey track`."""
    req: dict[str, Any] = {"samples": args.samples, "pans": args.pans, "write": not args.no_write}
    if args.stations:
        req["stations_mm"] = list(args.stations)
    for key, value in (
        ("max_corner_sigma_mm", args.max_corner_sigma), ("max_radius_sigma_mm",
        args.max_radius_sigma), ("max_rms_mm", args.max_rms), ("speed_mm_s", args.speed),
    ):  # fmt: skip
        if value is not None:
            req[key] = value
    return follow(args, "survey_track", req)


def run_calibrate_rangefinder(args: argparse.Namespace) -> int:
    """`orbitar calibrate rangefinder`."""
    req: dict[str, Any] = {"samples": args.samples, "pans": args.pans, "write": not args.no_write}
    try:
        if args.aims:
            req["aims"] = _json(args.aims)
    except (OSError, ValueError) as exc:
        return _fail(str(exc))
    if args.stations:
        req["stations_mm"] = list(args.stations)
    if args.tilts_deg:
        req["tilts_rad"] = [math.radians(t) for t in args.tilts_deg]
    for key, value in (("max_rms_mm", args.max_rms), ("speed_mm_s", args.speed)):
        if value is not None:
            req[key] = value
    return follow(args, "calibrate_rangefinder", req)


def _json(path: str) -> Any:
    """A JSON file's content (ValueError naming the file)."""
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON: {exc}") from exc


def follow(args: argparse.Namespace, op: str, req: dict[str, Any]) -> int:
    """Run `op` to its end with live progress; print and return the exit code."""
    view = ProgressView(sys.stderr)
    try:
        result = asyncio.run(_follow(args.socket, op, req, view))
    except KeyboardInterrupt:
        return _fail("interrupted: the run was cancelled, nothing written")
    except (ConnectionError, FileNotFoundError) as exc:
        return _fail(f"daemon not running? cannot reach {args.socket}: {exc}")
    except ControlRequestError as exc:
        return _fail(f"{op} refused: {exc}")
    except RunFailedError as exc:
        return _fail(str(exc))
    finally:
        view.finish()
    if args.json:
        emit(json.dumps(result, indent=2, default=str) + "\n")
    else:
        emit(result_text(result))
    return 0 if result.get("passed") else 1


async def _follow(path: str, op: str, req: dict[str, Any], view: ProgressView) -> dict[str, Any]:
    async with await ControlClient.connect_unix(path) as client:
        return await run_op(client, op, req, view.show)


def result_text(result: dict[str, Any]) -> str:
    """Verdict, reasons, table, coverage, where the report and the result went."""
    lines = ["PASS" if result.get("passed") else "FAIL"]
    lines += [f"  {r}" for r in result.get("reasons", [])]
    if result.get("table"):
        lines += ["", result["table"]]
    if result.get("coverage"):
        lines += ["", coverage.bars(result["coverage"])]
    lines.append("")
    lines.append(f"report: {result.get('report')}")
    written = result.get("written")
    if written:
        lines.append(f"written to {written} (previous version kept as a .bak)")
    elif result.get("passed"):
        lines.append("not written (--no-write, or the daemon has no rig file)")
    else:
        lines.append("nothing written")
    return "\n".join(lines) + "\n"


# the progress map's counts and how the line names them
COUNTS = (("accepted", "kept"), ("blurred", "blurred"), ("not_found", "no board"))


class ProgressView:
    """Progress on stderr: redrawn on a terminal, one line per view otherwise."""

    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.tty = out.isatty()
        self._last: tuple[Any, ...] = ()
        self._lines = 0

    def show(self, p: dict[str, Any]) -> None:
        """Draw one progress map."""
        key = (p.get("phase"), p.get("view"), p.get("accepted"))
        if key == self._last:
            return
        self._last = key
        head = (
            f"{p.get('phase', '?')}: view {p.get('view', 0)}/{p.get('of', p.get('planned', '?'))}"
        )
        # only the counts this run reports: a rangefinder run has no board to blur or lose
        head += "".join(f"  {name} {p[key]}" for key, name in COUNTS if key in p)
        if not self.tty:
            cov = p.get("coverage") or {}
            bars = " ".join(f"{k} {cov[k]:.2f}" for k in coverage.PARAMS if k in cov)
            self.out.write(head + (f"  coverage {bars}" if bars else "") + "\n")
            return
        text = head + "\n" + coverage.bars(p.get("coverage") or {}) + "\n"
        if self._lines:
            self.out.write(f"\x1b[{self._lines}A")
        self.out.write("".join(CLEAR_LINE + line + "\n" for line in text.splitlines()))
        self._lines = text.count("\n")
        self.out.flush()

    def finish(self) -> None:
        """Nothing to close: the bars stay on screen."""
        self.out.flush()


def _fail(message: str) -> int:
    print(f"orbitar: {message}", file=sys.stderr)
    return 1
