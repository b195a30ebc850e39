"""`orbitar daemon` on the in-memory controller, for tests that run the daemon as a process.

    python -m tests.service.fake_daemon [--unreachable] daemon --config PATH

The production entry point has no way to select a fake: this test module passes its own
factories to `host.service.main.run`, as an in-process test passes them to `Daemon`.
"""

from __future__ import annotations

import argparse
import sys

from host.config import Config
from host.control.api import ControllerLike, PoseSink
from host.service import main as daemon_main
from host.service.daemon import RecordTap
from host.service.wiring import rig_spec
from tests.fakes import MemoryController, MemoryFrameLoop


def run(argv: list[str]) -> int:
    """Parse `[--unreachable] daemon …` and run the daemon on the fake."""
    unreachable = "--unreachable" in argv
    argv = [a for a in argv if a != "--unreachable"]
    parser = argparse.ArgumentParser(prog="fake_daemon")
    sub = parser.add_subparsers(dest="command", required=True)
    daemon_main.add_parser(sub)
    args = parser.parse_args(argv)

    def controller(config: Config, tap: RecordTap) -> ControllerLike:
        return MemoryController(fail_connect=unreachable)

    def frames(
        config: Config, ctl: ControllerLike, sink: PoseSink, tap: RecordTap
    ) -> MemoryFrameLoop:
        assert isinstance(ctl, MemoryController)
        rig = rig_spec(config)  # the rig file's camera rate and track height
        return MemoryFrameLoop(ctl, sink, rig.camera.fps, float(rig.track.placement.matrix[2, 3]))

    return daemon_main.run(args, controller, frames)


if __name__ == "__main__":
    sys.exit(run(sys.argv[1:]))
