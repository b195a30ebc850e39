"""`orbitar fleet`: every rig on the bus and its state, live, from liveliness and published data.

The parser is registered without importing Zenoh (`add_parser`); the session opens only when
the command runs.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, TextIO

CLEAR_SCREEN = "\x1b[H\x1b[2J"


@dataclass
class RigView:
    """What the fleet knows of one rig."""

    alive: bool = False
    state: dict[str, Any] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    seen_s: float = 0.0  # host monotonic time of the last message

    def row(self, rig: str, now_s: float) -> dict[str, Any]:
        """A plain summary for the table and --json."""
        position = self.state.get("position_mm")
        return {
            "rig": rig,
            "alive": self.alive,
            "state": self.state.get("state", "?"),
            "position_mm": None if position is None else round(float(position), 1),
            "link_up": self.stats.get("link_up"),
            "fps": self.stats.get("fps"),
            "age_s": round(now_s - self.seen_s, 1) if self.seen_s else None,
        }


class Fleet:
    """Rigs seen on a Zenoh session; updated from Zenoh's threads, read from any."""

    def __init__(self, session: Any) -> None:
        self.session = session
        self.rigs: dict[str, RigView] = {}
        self.bad_payloads = 0
        self._lock = threading.Lock()
        self._subscriptions: list[Any] = []

    def start(self) -> None:
        """Follow liveliness and state with history (rigs already up, and the state they last
        published, are reported at once), and statistics as they come."""
        import zenoh.ext

        from host.bus.messages import ALIVE, key

        liveliness = self.session.liveliness()
        history = zenoh.ext.HistoryConfig(detect_late_publishers=True)
        self._subscriptions = [
            liveliness.declare_subscriber(key("*", ALIVE), self._on_alive, history=True),
            zenoh.ext.declare_advanced_subscriber(
                self.session, key("*", "state"), self._on_data("state"), history=history
            ),
            self.session.declare_subscriber(key("*", "stats"), self._on_data("stats")),
        ]

    def rows(self) -> list[dict[str, Any]]:
        """One summary per rig, sorted by name."""
        now_s = time.monotonic()
        with self._lock:
            return [view.row(rig, now_s) for rig, view in sorted(self.rigs.items())]

    def close(self) -> None:
        """Stop following."""
        for subscription in self._subscriptions:
            subscription.undeclare()
        self._subscriptions.clear()

    def _view(self, rig: str) -> RigView:
        return self.rigs.setdefault(rig, RigView())

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        from host.bus.messages import rig_of

        with self._lock:
            view = self._view(rig_of(str(sample.key_expr)))
            view.alive = sample.kind == zenoh.SampleKind.PUT
            view.seen_s = time.monotonic()

    def _on_data(self, topic: str) -> Any:
        from host.bus.messages import rig_of, unpack

        def on_sample(sample: Any) -> None:
            try:
                data = unpack(sample.payload.to_bytes())
            except ValueError:
                self.bad_payloads += 1
                return
            with self._lock:
                view = self._view(rig_of(str(sample.key_expr)))
                setattr(view, topic, data)
                view.seen_s = time.monotonic()

        return on_sample


def format_table(rows: list[dict[str, Any]]) -> str:
    """The rigs as aligned text, for a person."""
    if not rows:
        return "no rigs on the bus\n"
    lines = [f"{'RIG':<20} {'ALIVE':<6} {'STATE':<10} {'POSITION':>12} {'LINK':<5} {'AGE':>7}"]
    for row in rows:
        position = "-" if row["position_mm"] is None else f"{row['position_mm']:.1f} mm"
        link = {True: "up", False: "down"}.get(row["link_up"], "?")
        age = "-" if row["age_s"] is None else f"{row['age_s']:.1f} s"
        alive = "yes" if row["alive"] else "gone"
        lines.append(
            f"{row['rig']:<20} {alive:<6} {row['state']:<10} {position:>12} {link:<5} {age:>7}"
        )
    return "\n".join(lines) + "\n"


def add_parser(sub: Any) -> None:
    """Register `orbitar fleet`."""
    parser = sub.add_parser("fleet", help="list the rigs on the bus and their state, live")
    parser.add_argument("--config", help="take [bus] endpoints and mode from this file")
    parser.add_argument("--connect", action="append", default=[], help="endpoint (repeatable)")
    parser.add_argument("--listen", action="append", default=[], help="endpoint (repeatable)")
    parser.add_argument("--mode", choices=("peer", "client"), default=None)
    parser.add_argument("--scouting", action="store_true", help="multicast scouting on")
    parser.add_argument("--once", action="store_true", help="print once after --wait and exit")
    parser.add_argument("--wait", type=float, default=1.5, help="seconds to listen before --once")
    parser.add_argument("--interval", type=float, default=1.0, help="redraw period, s")
    parser.add_argument("--json", action="store_true", help="JSON lines instead of a table")
    parser.set_defaults(handler=run_fleet)


def run_fleet(args: argparse.Namespace, out: TextIO = sys.stdout) -> int:
    """Open a session, follow the rigs, print them."""
    import zenoh

    from host.bus.session import zenoh_config

    settings = _settings(args)
    if settings is None:
        return 2
    try:
        session = zenoh.open(zenoh_config(*settings))
    except zenoh.ZError as exc:
        print(f"orbitar fleet: cannot open the bus: {exc}", file=sys.stderr)
        return 1
    fleet = Fleet(session)
    try:
        fleet.start()
        return _show(fleet, args, out)
    except KeyboardInterrupt:
        return 0
    finally:
        fleet.close()
        session.close()


def _settings(args: argparse.Namespace) -> tuple[str, list[str], list[str], bool] | None:
    """Mode, listen, connect and scouting from the flags over the config file's [bus]."""
    mode, scouting = "peer", False
    listen: list[str] = []
    connect: list[str] = []
    if args.config:
        from host.config import load_config
        from host.config_fields import ConfigError

        try:
            bus = load_config(args.config).bus
        except (ConfigError, OSError) as exc:
            print(f"orbitar fleet: {exc}", file=sys.stderr)
            return None
        mode, scouting = bus.mode, bus.scouting
        listen, connect = list(bus.listen), list(bus.connect)
    mode = args.mode or mode
    return mode, args.listen or listen, args.connect or connect, args.scouting or scouting


def _show(fleet: Fleet, args: argparse.Namespace, out: TextIO) -> int:
    """Print once (--once) or redraw until interrupted."""
    if args.once:
        time.sleep(args.wait)
        _print(fleet.rows(), args.json, out, clear=False)
        return 0
    while True:
        _print(fleet.rows(), args.json, out, clear=out.isatty())
        time.sleep(args.interval)


def _print(rows: list[dict[str, Any]], as_json: bool, out: TextIO, clear: bool) -> None:
    if as_json:
        out.write(json.dumps({"t_unix_s": round(time.time(), 3), "rigs": rows}) + "\n")
    else:
        out.write((CLEAR_SCREEN if clear else "") + format_table(rows))
    out.flush()
