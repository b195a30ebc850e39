"""How long `orbitar status` takes before it does anything: imports and wall time.

Runs `python -X importtime -m host.cli status --help` several times, beside two peers measured
in the same run: a bare interpreter (`python -c pass`, the floor) and importing every
subcommand's module, which is what the CLI paid before subcommands were loaded lazily.

    .venv/bin/python benchmarks/bench_cli.py [--runs 7]

Prints `metric: value` lines (milliseconds, medians over the runs).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

STATUS_HELP = ["-m", "host.cli", "status", "--help"]
EVERY_COMMAND = [
    "-c",
    "import importlib, host.cli\n"
    "for c in {c.module for c in host.cli.COMMANDS.values()}: importlib.import_module(c)",
]
BARE = ["-c", "pass"]
STARTUP = ("site", "encodings")  # what every interpreter imports before the first line


def import_ms(args: list[str]) -> tuple[float, float]:
    """(wall ms, import ms excluding site) of one interpreter run with -X importtime."""
    t0 = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-X", "importtime", *args], capture_output=True, text=True, check=True
    )
    wall_ms = (time.perf_counter() - t0) * 1e3
    total_us = 0
    for line in done.stderr.splitlines():
        if not line.startswith("import time:") or "cumulative" in line:
            continue
        _, cumulative, name = line[len("import time:") :].split("|")
        top_level = not name[1:].startswith(" ")  # nested imports are indented further
        if top_level and name.strip() not in STARTUP:
            total_us += int(cumulative)
    return wall_ms, total_us / 1e3


def median_of(args: list[str], runs: int) -> tuple[float, float]:
    """Medians of wall and import time over `runs` runs."""
    samples = [import_ms(args) for _ in range(runs)]
    return statistics.median(s[0] for s in samples), statistics.median(s[1] for s in samples)


def main() -> None:
    """Measure and print."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7)
    runs = parser.parse_args().runs
    for label, args in (
        ("status_help", STATUS_HELP),
        ("peer_every_command_module", EVERY_COMMAND),
        ("peer_bare_python", BARE),
    ):
        wall, imports = median_of(args, runs)
        print(f"cli_{label}_wall_ms: {wall:.1f}")
        print(f"cli_{label}_import_ms: {imports:.1f}")


if __name__ == "__main__":
    main()
