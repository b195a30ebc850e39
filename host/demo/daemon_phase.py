"""The daemon itself, in process, on the simulated rig: what commissioning runs against.

An installer commissions a rig through the running daemon's control socket (`orbitar calibrate
…`, `orbitar survey …`). The demo does the same: `running_daemon` starts the daemon's own code
(`host.service.daemon.Daemon` with the real `wiring` factories) on the simulator's link, with
the simulator's camera as its frame source and the demo's rig file as `[rig] path`, and yields
the control socket's path. Commissioning clients connect there as from another process; what
they write into the rig file the daemon picks up on SIGHUP (`Daemon.reload`). Leaving the
context stops the daemon and releases the link, so the experiments can open it afterwards.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.xbee import CONTROLLER_ADDR64, XBeeModule
from host.config import Config, loads_config
from host.demo.world import SERIAL_BAUD, SimWorld
from host.frames.sources import FrameSource
from host.service import wiring
from host.service.daemon import Daemon

SOCKET_NAME = "control.sock"
START_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 10.0
HEARTBEAT_MS = 100


@dataclass
class RunningDaemon:
    """A daemon serving the simulated rig: its control socket, and the object (for SIGHUP)."""

    daemon: Daemon
    socket_path: Path
    config_path: Path
    rig_path: Path

    async def reload(self) -> list[str]:
        """What SIGHUP does: reread the config and the rig file; the sections applied."""
        return await self.daemon.reload()


def daemon_config_text(world: SimWorld, rig_path: Path, workdir: Path) -> str:
    """The daemon's TOML for this simulated rig: its link, the rig file, a private socket."""
    # Heartbeats at 100 ms: five per controller watchdog period (500 ms), as the demo's own
    # link has, so a busy machine does not stop the trolley mid-calibration.
    link = _link_table(world) + f"\nheartbeat_ms = {HEARTBEAT_MS}"
    return (
        f'{link}\n[rig]\npath = {_q(rig_path)}\n[camera]\nsource = "sim"\n'
        f"[control]\nsocket_path = {_q(workdir / SOCKET_NAME)}\n"
        "[systemd]\nready_grace_s = 0.0\n"
    )


@contextlib.asynccontextmanager
async def running_daemon(
    world: SimWorld, rig_path: Path, workdir: Path, camera: FrameSource | None = None
) -> AsyncIterator[RunningDaemon]:
    """Run the daemon on `world` (already started) until the block ends."""
    workdir.mkdir(parents=True, exist_ok=True)
    config_path = workdir / "orbitar.toml"
    config_path.write_text(daemon_config_text(world, rig_path, workdir), encoding="utf-8")
    config: Config = loads_config(config_path.read_text(encoding="utf-8"))
    frames = functools.partial(wiring.frame_loop_factory, camera=camera)
    daemon = Daemon(config, wiring.controller_factory, frames, config_path=config_path)
    task = asyncio.create_task(daemon.run())
    socket_path = workdir / SOCKET_NAME
    try:
        await _wait_for(socket_path, task)
        yield RunningDaemon(daemon, socket_path, config_path, rig_path)
    finally:
        daemon.request_stop()
        with contextlib.suppress(Exception):
            await asyncio.wait_for(task, STOP_TIMEOUT_S)


async def _wait_for(socket_path: Path, task: asyncio.Task[int]) -> None:
    """Until the control socket answers; the daemon's own error if it stopped first. (A socket
    file left by an earlier run in the same --out directory exists but refuses.)"""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + START_TIMEOUT_S
    while not await _answers(socket_path):
        if task.done():
            raise RuntimeError(f"the daemon stopped at start (exit {task.result()})")
        if loop.time() > deadline:
            raise TimeoutError(f"the daemon did not open {socket_path}")
        await asyncio.sleep(0.02)


async def _answers(socket_path: Path) -> bool:
    """Whether something accepts connections on the socket."""
    try:
        _, writer = await asyncio.open_unix_connection(str(socket_path))
    except OSError:
        return False
    writer.close()
    with contextlib.suppress(OSError):
        await writer.wait_closed()
    return True


def _link_table(world: SimWorld) -> str:
    """`[link]` for the world's emulator, as `orbitar sim` prints it for a real daemon."""
    emu = world.emulator
    if isinstance(emu, PtyUart):
        return f'[link]\nkind = "serial"\nurl = {_q(emu.path)}\nbaud = {SERIAL_BAUD}'
    if isinstance(emu, XBeeModule):
        return (
            f'[link]\nkind = "xbee"\nurl = {_q(emu.path)}\nbaud = {SERIAL_BAUD}\n'
            f'xbee_address = "{CONTROLLER_ADDR64:016X}"\nxbee_api_mode = 2'
        )
    return f'[link]\nkind = "can"\ncan_interface = "virtual"\ncan_channel = {_q(world.can_channel)}'


def _q(value: object) -> str:
    """A TOML basic string."""
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'
