"""Run the suite against a transport URL and report per check and per rule."""

from __future__ import annotations

import argparse
import asyncio
import re
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from host.conformance import (  # noqa: F401  (register the checks)
    checks_batches,
    checks_clock,
    checks_link,
    checks_state,
)
from host.conformance.base import CHECKS, Check, Context, Options
from host.conformance.wire import ConformanceError, NotApplicable, WireClient
from host.transport import Transport, TransportConfigError, TransportError, transport_from_config

SPEC_PATH = Path(__file__).resolve().parents[2] / "protocol" / "PROTOCOL.md"
RULE_ID = re.compile(r"\[(R-[A-Z]+-\d+)\]")
CHECK_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class Outcome:
    """How one check ended."""

    check: Check
    status: str  # "pass", "fail" or "skip"
    detail: str = ""
    seconds: float = 0.0


@dataclass
class SuiteResult:
    """Every check's outcome; `ok` when none failed."""

    outcomes: list[Outcome] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """No check failed."""
        return all(o.status != "fail" for o in self.outcomes)

    def failed(self) -> list[str]:
        """Names of the failed checks."""
        return [o.check.name for o in self.outcomes if o.status == "fail"]

    def rules_failed(self) -> set[str]:
        """Rule ids covered by a failed check."""
        return {r for o in self.outcomes if o.status == "fail" for r in o.check.rules}


def spec_rules(text: str | None = None) -> set[str]:
    """Every rule id PROTOCOL.md states."""
    return set(RULE_ID.findall(SPEC_PATH.read_text(encoding="utf-8") if text is None else text))


def covered_rules() -> set[str]:
    """Every rule id some check names."""
    return {r for c in CHECKS for r in c.rules}


def select(only: Sequence[str] = ()) -> list[Check]:
    """The checks whose name contains one of `only`, or that cover one of those rule ids."""
    if not only:
        return list(CHECKS)
    return [c for c in CHECKS if any(o in c.name or o in c.rules for o in only)]


async def run_suite(
    transport: Transport, options: Options | None = None, only: Sequence[str] = ()
) -> SuiteResult:
    """Open the transport, run the selected checks one after another, close it."""
    options = options or Options()
    client = WireClient(transport)
    await client.open()
    result = SuiteResult()
    try:
        ctx = Context(client, options)
        for chk in select(only):
            result.outcomes.append(await _run_one(ctx, chk))
    finally:
        await client.close()
    return result


async def _run_one(ctx: Context, chk: Check) -> Outcome:
    """One check: pass, fail with the reason, or skip when it would move and may not."""
    if chk.motion and not ctx.options.motion:
        return Outcome(chk, "skip", "moves the trolley (--no-motion)")
    t0 = time.monotonic()
    try:
        async with asyncio.timeout(CHECK_TIMEOUT_S):
            await chk.fn(ctx)
    except NotApplicable as exc:
        return Outcome(chk, "skip", str(exc), time.monotonic() - t0)
    except ConformanceError as exc:
        return Outcome(chk, "fail", str(exc), time.monotonic() - t0)
    except TimeoutError:
        return Outcome(chk, "fail", f"did not finish in {CHECK_TIMEOUT_S:.0f} s")
    except TransportError as exc:
        return Outcome(chk, "fail", f"link: {exc}", time.monotonic() - t0)
    ctx.client.heartbeats = True
    return Outcome(chk, "pass", "", time.monotonic() - t0)


def report(result: SuiteResult) -> str:
    """A plain-text report: one line per check, then the rule tally."""
    lines = []
    for o in result.outcomes:
        rules = " ".join(o.check.rules)
        detail = f"  -- {o.detail}" if o.detail else ""
        lines.append(f"{o.status.upper():4} {o.seconds:5.1f}s  {o.check.name}  [{rules}]{detail}")
    counts = {s: sum(o.status == s for o in result.outcomes) for s in ("pass", "fail", "skip")}
    lines.append(
        f"checks: {counts['pass']} passed, {counts['fail']} failed, {counts['skip']} skipped; "
        f"rules failed: {' '.join(sorted(result.rules_failed())) or 'none'}"
    )
    return "\n".join(lines)


def add_parser(sub: Any) -> None:
    """`orbitar conformance URL`: registered in host/cli.py's subcommand table."""
    p = sub.add_parser("conformance", help="check a controller against PROTOCOL.md over its wire")
    _arguments(p)
    p.set_defaults(handler=_cli)


def _arguments(p: argparse.ArgumentParser) -> None:
    """The suite's options."""
    p.add_argument("url", help="any link URL the host takes: /dev/ttyUSB0, xbee://…, can://…")
    p.add_argument("--no-motion", action="store_true", help="skip the checks that move")
    p.add_argument(
        "--home-speed", type=int, default=0, metavar="UM_S", help="HOME speed (0: controller's)"
    )
    p.add_argument("--only", action="append", default=[], help="check name part or rule id")


def _cli(args: argparse.Namespace) -> int:
    """Run from parsed arguments; exit 0 when every selected check passed."""
    try:
        transport = transport_from_config({"url": args.url})
    except TransportConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    options = Options(motion=not args.no_motion, home_speed_um_s=args.home_speed)
    try:
        result = asyncio.run(run_suite(transport, options, args.only))
    except TransportError as exc:
        print(f"error: cannot reach the controller at {args.url}: {exc}", file=sys.stderr)
        return 2
    print(report(result))
    return 0 if result.ok else 1


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m host.conformance`."""
    p = argparse.ArgumentParser(prog="python -m host.conformance", description=__doc__)
    _arguments(p)
    return _cli(p.parse_args(argv))
