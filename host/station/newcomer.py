"""`orbitar demo --ui`: the simulated rig, the daemon and the station, until Ctrl-C.

For someone who has just cloned the project: the emulated controller (firmware mirror and plant)
runs in real time behind a pty, the daemon reaches it over its serial link exactly as on a rig,
a simulated camera renders the true scene, and the station serves the live AR at a printed URL.
The daemon is configured as commissioning would leave it (nominal rig, surveyed marks); the
simulator's truth reaches it only as camera pixels.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import math
import secrets
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from host.config import Config, config_from_dict
from host.service.daemon import Daemon

DEMO_PORT = 8080
WORKPIECE_W = (-300.0, -300.0, 0.0)  # where the demo's manipulator stands (as in `orbitar demo`)
TILT_MAX_DEG = 60.0
HOME_MIN_SLOPE = 0.7  # |∂range/∂s| of the beam the home survey is taken with


def demo_config(link_url: str, rig_path: Path, socket_path: str, ui: dict[str, Any]) -> Config:
    """The daemon's configuration for the simulated rig (the rig itself is the rig file)."""
    return config_from_dict(
        {
            "link": {"kind": "serial", "url": link_url, "baud": 115200},
            "rig": {"path": str(rig_path)},
            "camera": {"source": "none"},
            "control": {"socket_path": socket_path},
            "systemd": {"ready_grace_s": 5.0},
            "ui": {"enabled": True, **ui},
        }
    )


async def run_newcomer(host: str, port: int, seed: int) -> int:
    """Start everything, print the URL, serve until SIGINT/SIGTERM."""
    from host.demo.rigs import DemoRigs, model_of
    from host.demo.world import SimCameraSource, SimWorld
    from host.rig import save_rig
    from host.service import wiring

    rigs = DemoRigs.make(None, seed, tolerances=False)  # the host is handed the simulated rig
    rig = rigs.true_kinematics()
    sc = rigs.scenario(seed)
    world = SimWorld(sc, "pty")
    await world.start()
    workdir = Path(tempfile.mkdtemp(prefix="orbitar-demo-ui-"))
    token, viewer = secrets.token_urlsafe(12), secrets.token_urlsafe(12)
    head = dataclasses.replace(rigs.host.head, tilt_max_rad=math.radians(TILT_MAX_DEG))
    save_rig(dataclasses.replace(rigs.host, head=head), workdir / "rig.toml", "orbitar demo --ui")
    ui = {"host": host, "port": port, "operator_token": token, "viewer_token": viewer}
    config = demo_config(world.link_path, workdir / "rig.toml", str(workdir / "ctl.sock"), ui)
    T_w_p = rigs.true_workpiece()
    model = model_of(rigs.truth)
    camera = SimCameraSource(world, rig, rigs.true_camera(), model, lambda t: T_w_p)
    factory = functools.partial(wiring.frame_loop_factory, camera=camera)
    try:
        daemon = Daemon(config, wiring.controller_factory, factory)
        jobs = [
            asyncio.create_task(_aim_when_up(daemon, rig, sc.track.start_s_mm)),
            asyncio.create_task(_announce(daemon, token, viewer, workdir)),
            asyncio.create_task(_survey_home(daemon, str(workdir / "ctl.sock"), rigs.host)),
        ]
        code = await daemon.run()
        for task in jobs:
            task.cancel()
        await asyncio.gather(*jobs, return_exceptions=True)
        return code
    finally:
        await world.stop()


async def _announce(daemon: Daemon, token: str, viewer: str, workdir: Path) -> None:
    """Print the URLs once the station listens."""
    while daemon.station is None or daemon.station.port is None:
        await asyncio.sleep(0.05)
    base = daemon.station.url
    print(f"Orbitar station (operator): {base}#token={token}")
    print(f"             (viewer only): {base}#token={viewer}")
    print(f"Terminal: orbitar watch --socket {workdir / 'ctl.sock'}")
    print("Hold a jog button to move the simulated trolley; Ctrl-C ends the demo.")
    sys.stdout.flush()


async def _survey_home(daemon: Daemon, socket_path: str, spec: Any) -> None:
    """After each homing, survey where the controller's zero is, as an installer would.

    The zero is the encoder index after the home switch, some way past the switch: the daemon's
    `survey_home` (the rangefinder on a surveyed wall along the track) measures it and writes it
    into the rig file, which the daemon then rereads.
    """
    from host.commissioning.client import RunFailedError, run_op
    from host.control.client import ControlClient
    from host.rig import build_kinematics, build_scene
    from host.station import pose_feed

    rig, scene = build_kinematics(spec), build_scene(spec)
    feed = pose_feed(daemon.controller)
    if feed is None or scene is None:
        return
    surveyed = False
    while True:
        await asyncio.sleep(0.2)
        snap = daemon.controller.snapshot()
        if not feed.homed:
            surveyed = False
        elif not surveyed and snap.get("state") == "READY":
            surveyed = True
            aim = home_aim(rig, scene, float(snap.get("position_mm") or 0.0) + feed.home_s_mm,
                           (spec.head.tilt_min_rad, math.radians(TILT_MAX_DEG)))  # fmt: skip
            if aim is None:
                print("(no surveyed wall along the track: the home stays the drawing's)")
                continue
            try:
                async with await ControlClient.connect_unix(socket_path) as client:
                    await run_op(client, "survey_home", {"pan_rad": aim[0], "tilt_rad": aim[1]})
            except (OSError, RunFailedError) as exc:
                print(f"(the home survey failed: {exc})", file=sys.stderr)


def home_aim(
    rig: Any, scene: Any, s_mm: float, tilt_limits: tuple[float, float]
) -> tuple[float, float] | None:
    """Head angles whose beam meets a surveyed surface most steeply along the track."""
    from host.geometry.rangefinder import range_at

    best, best_slope = None, HOME_MIN_SLOPE
    for pan in (0.0, math.pi):
        for tilt in np.linspace(tilt_limits[0], tilt_limits[1], 19):
            a = range_at(rig, scene, s_mm - 1.0, pan, float(tilt))
            b = range_at(rig, scene, s_mm + 1.0, pan, float(tilt))
            if a is None or b is None:
                continue
            slope = abs(b.distance_mm - a.distance_mm) / 2.0
            if slope > best_slope:
                best, best_slope = (pan, float(tilt)), slope
    return best


async def _aim_when_up(daemon: Daemon, rig: Any, start_s_mm: float) -> None:
    """Point the head at the workpiece once the link is up, so the first look shows the AR."""
    while not daemon.controller.connected:
        await asyncio.sleep(0.1)
    target = np.array(WORKPIECE_W) + np.array([0.0, 0.0, 600.0])
    pan, tilt = rig.aim(start_s_mm, target)
    try:
        await daemon.controller.set_head(pan, min(tilt, math.radians(TILT_MAX_DEG)))
    except Exception as exc:  # the newcomer can still aim it from the page
        print(f"(could not aim the head: {exc})", file=sys.stderr)


def main(args: Any) -> int:
    """`orbitar demo --ui [--ui-host H] [--ui-port P]`."""
    from host.service.logsetup import setup_logging

    setup_logging("warning")
    host = getattr(args, "ui_host", "127.0.0.1")
    port = getattr(args, "ui_port", DEMO_PORT)
    try:
        return asyncio.run(run_newcomer(host, port, args.seed))
    except KeyboardInterrupt:
        return 0
