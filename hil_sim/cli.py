"""`orbitar sim`: the emulated controller (firmware mirror + plant) in real time behind a link.

Runs until Ctrl-C or SIGTERM and prints where to connect: the pty (or TCP URL) and the `[link]`
lines for the daemon's configuration. Options come from the command line, from `--config FILE`
(a TOML table of the same options, underscores for dashes), or the defaults, in that order of
precedence. The simulator modules are imported only when the command runs, so registering the
subcommand costs the host CLI nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import math
import signal
import sys
import tomllib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TextIO

if TYPE_CHECKING:  # the simulator is imported only when the command runs
    from hil_sim.links.faults import FaultConfig
    from hil_sim.runner import RealtimeRunner
    from hil_sim.scenario import Scenario

LINKS = ("pty", "tcp", "xbee", "can")
DEFAULT_BAUD = 115200
DEFAULT_CAN_BITRATE = 500_000
SLCAN_BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)
EXIT_BAD_OPTIONS = 2


@dataclass(frozen=True)
class SimOptions:
    """Everything `orbitar sim` can be told; the defaults are the paper's rig on a clean pty."""

    link: str = "pty"
    link_path: str | None = None
    baud: int = DEFAULT_BAUD
    port: int = 0  # tcp: 0 picks a free port
    api_mode: int = 2  # xbee
    node_id: int = 1  # can
    bitrate: int = DEFAULT_CAN_BITRATE  # can
    seed: int = 1
    speed: float = 1.0
    elongation: float = 0.0
    marks: tuple[float, ...] = ()
    drop_rate: float = 0.0
    bit_error_rate: float = 0.0
    latency_ms: float = 0.0
    jitter_ms: float = 0.0
    rig: str | None = None  # a rig file: the simulated (true) rig; None: the paper's rig
    tolerances: bool = False  # draw seeded installation tolerances around the rig file


class SimOptionsError(ValueError):
    """Bad options; `problems` names each key and the reason."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("; ".join(problems))
        self.problems = problems


Check = Callable[[Any], str | None]  # a reason, or None when the value is fine


def _number(lo: float, hi: float, integer: bool = False) -> Check:
    """A finite number (an integer if asked) within [lo, hi]."""

    def check(value: Any) -> str | None:
        if isinstance(value, bool) or not isinstance(value, int | float):
            return "expected an integer" if integer else "expected a number"
        if integer and not isinstance(value, int):
            return "expected an integer"
        if not math.isfinite(value) or not lo <= value <= hi:
            return f"must be within [{lo:g}, {hi:g}]"
        return None

    return check


def _choice(*choices: Any) -> Check:
    """One of the given values."""
    return lambda v: None if v in choices else f"must be one of {', '.join(map(str, choices))}"


def _path(value: Any) -> str | None:
    """A non-empty path string."""
    return None if isinstance(value, str) and value else "expected a non-empty path"


def _marks(value: Any) -> str | None:
    """A list of arc lengths in mm."""
    if not isinstance(value, list | tuple):
        return "expected a list of positions in mm"
    bad = [v for v in value if _number(-1e6, 1e6)(v) is not None]
    return f"not positions in mm: {bad}" if bad else None


CHECKS: dict[str, Check] = {
    "link": _choice(*LINKS),
    "link_path": _path,
    "baud": _number(1200, 4_000_000, integer=True),
    "port": _number(0, 65535, integer=True),
    "api_mode": _choice(1, 2),
    "node_id": _number(1, 127, integer=True),
    "bitrate": _choice(*SLCAN_BITRATES),
    "seed": _number(0, 2**63 - 1, integer=True),
    "speed": _number(0.01, 100.0),
    "elongation": _number(0.0, 0.1),
    "marks": _marks,
    "drop_rate": _number(0.0, 1.0),
    "bit_error_rate": _number(0.0, 1.0),
    "latency_ms": _number(0.0, 10_000.0),
    "jitter_ms": _number(0.0, 10_000.0),
    "rig": _path,
    "tolerances": lambda v: None if isinstance(v, bool) else "expected true or false",
}


def build_options(file_table: Mapping[str, Any], cli: Mapping[str, Any]) -> SimOptions:
    """Defaults, then the file, then the command line; SimOptionsError lists every problem."""
    problems = [f"{key}: unknown key (known: {', '.join(CHECKS)})" for key in file_table]
    problems = [p for p, key in zip(problems, file_table, strict=True) if key not in CHECKS]
    merged = {k: v for k, v in file_table.items() if k in CHECKS}
    merged.update({k: v for k, v in cli.items() if v is not None})
    for key, value in merged.items():
        reason = CHECKS[key](value)
        if reason is not None:
            problems.append(f"{key} = {value!r}: {reason}")
    if problems:
        raise SimOptionsError(problems)
    if "marks" in merged:
        merged["marks"] = tuple(float(m) for m in merged["marks"])
    return SimOptions(**merged)


def load_table(path: str) -> dict[str, Any]:
    """The TOML file's top-level table (an optional [sim] table is accepted too)."""
    try:
        table = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise SimOptionsError([f"{path}: cannot read: {exc}"]) from exc
    except tomllib.TOMLDecodeError as exc:
        raise SimOptionsError([f"{path}: TOML syntax: {exc}"]) from exc
    sim = table.get("sim")
    return dict(sim) if isinstance(sim, dict) and len(table) == 1 else table


def parse_marks(text: str) -> list[float]:
    """`--marks 1000,3000,5000` → [1000.0, 3000.0, 5000.0]."""
    try:
        return [float(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected MM,MM,… numbers") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of `orbitar sim` (every default None: the file and SimOptions fill them)."""
    add = parser.add_argument
    add("--link", choices=LINKS, help="pty (UART), tcp (socket://), xbee (API frames) or can")
    add("--link-path", help="stable symlink to the pty, e.g. /tmp/orbitar-sim")
    add("--baud", type=int, help=f"UART rate of pty/tcp/xbee (default {DEFAULT_BAUD})")
    add("--port", type=int, help="tcp: port on 127.0.0.1 (default: a free one)")
    add("--api-mode", type=int, help="xbee: API mode 1 or 2 (default 2)")
    add("--node-id", type=int, help="can: controller node id (default 1)")
    add("--bitrate", type=int, help=f"can: bus bit rate (default {DEFAULT_CAN_BITRATE})")
    add("--seed", type=int, help="simulator seed (default 1): same seed, same run")
    add("--speed", type=float, help="real-time factor (default 1.0)")
    add("--elongation", type=float, help="chain stretch, 0.005 = 0.5 %% (default 0)")
    add("--marks", type=parse_marks, help="reference marks along the track, MM,MM,…")
    add("--drop-rate", type=float, help="probability a link unit is lost")
    add("--bit-error-rate", type=float, help="probability each bit flips")
    add("--latency-ms", type=float, help="one-way link latency")
    add("--jitter-ms", type=float, help="uniform extra one-way delay up to this")
    add("--rig", help="rig file (the daemon's schema) to simulate as the true rig")
    add(
        "--tolerances",
        action="store_true",
        default=None,
        help="build the rig off its file by seeded installation tolerances (hil_sim.true_rig)",
    )
    add("--config", help="TOML file with the same options (underscores for dashes)")


def add_parser(subparsers: Any) -> None:
    """Register `orbitar sim`."""
    parser = subparsers.add_parser(
        "sim", help="run the emulated controller behind a pty, TCP, XBee or CAN link"
    )
    add_arguments(parser)
    parser.set_defaults(handler=run)


def options_from_args(args: argparse.Namespace) -> SimOptions:
    """SimOptions from parsed arguments and the optional --config file."""
    table = load_table(args.config) if args.config else {}
    cli = {f.name: getattr(args, f.name, None) for f in dataclasses.fields(SimOptions)}
    return build_options(table, cli)


def run(args: argparse.Namespace) -> int:
    """Run the emulator until SIGINT/SIGTERM; 0 then, 2 for bad options."""
    try:
        options = options_from_args(args)
        make_scenario(options)  # a bad rig file is a bad option: named now, exit 2
    except SimOptionsError as exc:
        for problem in exc.problems:
            print(f"orbitar sim: {problem}", file=sys.stderr)
        return EXIT_BAD_OPTIONS
    try:
        return asyncio.run(serve(options, sys.stdout))
    except OSError as exc:  # the port is taken, the symlink's directory is missing, …
        print(f"orbitar sim: {exc}", file=sys.stderr)
        return 1


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m hil_sim [options]`."""
    parser = argparse.ArgumentParser(prog="python -m hil_sim", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


def stop_on_signals(stop: asyncio.Event) -> Callable[[], None]:
    """SIGINT and SIGTERM set `stop`; returns the function that gives the signals back."""
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)

    def restore() -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(RuntimeError):
                loop.remove_signal_handler(sig)

    return restore


def say(out: TextIO, *lines: str) -> None:
    """Print and flush at once: a parent reading our pipe must see the lines now."""
    out.write("".join(line + "\n" for line in lines))
    out.flush()


# ---- running the emulator ----------------------------------------------------------------


class Emulator(Protocol):
    """What every link emulator offers."""

    async def start(self) -> None: ...

    async def stop(self) -> None: ...


async def serve(options: SimOptions, out: TextIO) -> int:
    """Start simulator and link, print where to connect, run until a signal; 0 at the end."""
    stop = asyncio.Event()
    restore = stop_on_signals(stop)
    runner = make_runner(options)
    emulator = make_emulator(options, runner)
    try:
        await emulator.start()
        runner.start()
        say(out, *connection_text(options, emulator))
        await stop.wait()
    finally:
        await emulator.stop()
        runner.stop()
        restore()
    say(out, f"orbitar sim: stopped; late ticks {runner.late_ticks}")
    return 0


def make_runner(options: SimOptions) -> RealtimeRunner:
    """The rig (the paper's or --rig's, tolerances if asked) paced at `speed` × real time."""
    from hil_sim.runner import RealtimeRunner, Simulation

    return RealtimeRunner(Simulation(make_scenario(options)), speed=options.speed)


def make_scenario(options: SimOptions) -> Scenario:
    """The scenario the options describe; SimOptionsError names a bad rig file."""
    from hil_sim.rig_scenario import scenario_for_rig
    from hil_sim.scenario import ChainConfig, Scenario, TrackConfig
    from hil_sim.true_rig import Tolerances, true_rig
    from host.rig import RigError, RigSpec, load_rig

    if options.rig is None and not options.tolerances:
        return Scenario(
            seed=options.seed,
            chain=ChainConfig(elongation=options.elongation),
            track=TrackConfig(reference_marks_mm=options.marks),
        )
    try:
        nominal = RigSpec() if options.rig is None else load_rig(options.rig)
    except RigError as exc:
        raise SimOptionsError([f"rig: {p}" for p in exc.problems]) from None
    tol = Tolerances() if options.tolerances else Tolerances.off()
    truth = true_rig(nominal, options.seed, tol)
    sc = scenario_for_rig(truth, options.seed, options.elongation)
    if options.marks:
        sc.track.reference_marks_mm = options.marks
    return sc


def fault_config(options: SimOptions, salt: int) -> FaultConfig:
    """The fault options for one direction (seeded from the run's seed)."""
    from hil_sim.links.faults import FaultConfig

    return FaultConfig(
        drop_rate=options.drop_rate,
        bit_error_rate=options.bit_error_rate,
        latency_s=options.latency_ms / 1000.0,
        jitter_s=options.jitter_ms / 1000.0,
        seed=options.seed * 4 + salt,
    )


def make_emulator(options: SimOptions, runner: RealtimeRunner) -> Emulator:
    """The chosen link emulator in front of the runner's port."""
    from hil_sim.links.can_node import SlcanAdapter
    from hil_sim.links.endpoint import SimPortEndpoint
    from hil_sim.links.pty_uart import PtyUart
    from hil_sim.links.tcp import TcpLink
    from hil_sim.links.xbee import XBeeModule

    endpoint = SimPortEndpoint(runner.port, asyncio.get_running_loop())
    down, up = fault_config(options, 0), fault_config(options, 1)
    path = options.link_path
    if options.link == "pty":
        return PtyUart(endpoint, options.baud, down, up, path)
    if options.link == "tcp":
        return TcpLink(endpoint, options.baud, down, up, options.port)
    if options.link == "xbee":
        return XBeeModule(endpoint, options.api_mode, options.baud, air_faults=down, link_path=path)
    return SlcanAdapter(endpoint, options.node_id, options.bitrate, down, path)


def connection_text(options: SimOptions, emulator: Emulator) -> list[str]:
    """What to tell the user: where to connect and the daemon's [link] lines."""
    head = [
        f"orbitar sim: emulated controller running (link {options.link}, seed {options.seed}, "
        f"speed {options.speed:g}x, rig {options.rig or 'the paper runway'}"
        f"{', with seeded tolerances' if options.tolerances else ''})"
    ]
    link = link_lines(options, emulator)
    tail = ["press Ctrl-C (or send SIGTERM) to stop"]
    rig = [] if options.rig is None else ["  [rig]", f'  path = "{options.rig}"']
    return head + [f"connect: {link[0]}", "daemon configuration:"] + link[1] + rig + tail


def link_lines(options: SimOptions, emulator: Emulator) -> tuple[str, list[str]]:
    """(where to connect, the [link] table for the daemon's TOML)."""
    path = str(getattr(emulator, "path", ""))
    device = _device_text(path)
    if options.link == "tcp":
        url = str(getattr(emulator, "url", ""))
        return url, _table(kind="serial", url=url, baud=options.baud)
    if options.link == "xbee":
        from hil_sim.links.xbee import CONTROLLER_ADDR64

        address = f"{CONTROLLER_ADDR64:016X}"
        where = f"{device} (XBee API mode {options.api_mode}, controller address {address})"
        table = _table(
            kind="xbee", url=path, baud=options.baud, xbee_address=address,
            xbee_api_mode=options.api_mode,
        )  # fmt: skip
        return where, table
    if options.link == "can":
        where = f"{device} (python-can interface slcan, node {options.node_id})"
        table = _table(
            kind="can", can_interface="slcan", can_channel=path,
            can_bitrate=options.bitrate, node_id=options.node_id,
        )  # fmt: skip
        return where, table
    return f"{device} at {options.baud} Bd", _table(kind="serial", url=path, baud=options.baud)


def _device_text(path: str) -> str:
    """`/tmp/orbitar-sim -> /dev/pts/5` for a symlink, else the pty path."""
    p = Path(path)
    with contextlib.suppress(OSError):
        if p.is_symlink():
            return f"{path} -> {p.readlink()}"
    return path


def _table(**values: Any) -> list[str]:
    """`[link]` and its TOML lines, indented for reading."""
    lines = ["  [link]"]
    for key, value in values.items():
        text = f'"{value}"' if isinstance(value, str) else str(value)
        lines.append(f"  {key} = {text}")
    return lines
