"""`orbitar daemon` on the real link: emulator and daemon as processes, a fake notify socket.

The emulator (`python -m hil_sim --link pty`) serves the firmware mirror on a pty; the daemon
reaches it through the configured serial link with no camera, so poses come from the encoder at a
fixed rate. The operator's CLI (`orbitar status/home/move`) drives the simulated trolley.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import signal
import socket
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from host.config import Config
from host.control.client import ControlClient
from tests.service.test_daemon import connect

CONFIG = """
[link]
kind = "serial"
url = "{dir}/sim"
baud = 115200
heartbeat_ms = 100
[rig]
path = "{dir}/rig.toml"
[camera]
source = "none"
[control]
socket_path = "{dir}/ctl.sock"
[systemd]
ready_grace_s = 30.0
status_interval_s = 0.5
"""
RIG = """
[track.home]
value_mm = 150.0
[track.marks]
s_mm = [250.0, 400.0]
[camera]
fps = 20.0
"""
WATCHDOG_USEC = "400000"
HOME_SPEED_UM_S = 150_000  # the default 50 mm/s would spend ~8 s of the test homing
POSITION_TOLERANCE_MM = 3.0
HOME_S_MM = 150.0  # the emulator's home switch; its zero is at the next index, a survey away


class Notifications:
    """Drains our NOTIFY_SOCKET in the background (its queue holds only ~10 datagrams)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.got: list[str] = []
        self._task = asyncio.create_task(self._drain())

    async def _drain(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            self.got.append((await loop.sock_recv(self.sock, 4096)).decode())

    async def wait_for(self, needle: str, timeout_s: float) -> str:
        """The first notification containing `needle`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for text in self.got:
                if needle in text:
                    return text
            await asyncio.sleep(0.02)
        raise TimeoutError(f"{needle} not in {self.got[-5:]}")

    async def close(self) -> None:
        """Stop draining and close the socket."""
        self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self._task
        self.sock.close()


@dataclass
class Rig:
    """The emulator, the daemon and the notify socket of one test."""

    sim: asyncio.subprocess.Process
    daemon: asyncio.subprocess.Process
    notes: Notifications
    dir: Path

    @property
    def socket(self) -> str:
        """The daemon's control socket."""
        return str(self.dir / "ctl.sock")


async def cli(rig: Rig, *args: str) -> tuple[int, str]:
    """`orbitar ARGS --socket …` as an operator types it; (exit code, stdout + stderr)."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.cli", *args, "--socket", rig.socket,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT,
    )  # fmt: skip
    out, _ = await asyncio.wait_for(proc.communicate(), 20.0)
    assert proc.returncode is not None
    return proc.returncode, out.decode()


async def status(rig: Rig) -> dict[str, Any]:
    """`orbitar status --json`, parsed."""
    code, out = await cli(rig, "status", "--json")
    assert code == 0, out
    result: dict[str, Any] = json.loads(out)
    return result


async def wait_until_at(
    client: ControlClient, target_mm: float, timeout_s: float, tol_mm: float = POSITION_TOLERANCE_MM
) -> None:
    """Poll the controller snapshot until it rests in READY within tol_mm of the target."""
    deadline = time.monotonic() + timeout_s
    last: dict[str, Any] = {}
    while time.monotonic() < deadline:
        last = (await client.request("status"))["controller"]
        position = last.get("position_mm")
        at = position is not None and abs(position - target_mm) < tol_mm
        if last.get("state") == "READY" and at:
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"not at {target_mm} mm: {last}")


async def start_sim(tmp_path: Path) -> asyncio.subprocess.Process:
    """The emulator behind a pty at tmp/sim, once it says it is ready."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "hil_sim", "--link", "pty", "--link-path", str(tmp_path / "sim"),
        "--marks", "250,400",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    assert proc.stdout is not None
    while b"press Ctrl-C" not in await asyncio.wait_for(proc.stdout.readline(), 20.0):
        assert proc.returncode is None
    return proc


async def start_daemon(tmp_path: Path) -> tuple[asyncio.subprocess.Process, Notifications]:
    """The daemon with the real link, a notify socket of ours and a watchdog period."""
    config = tmp_path / "orbitar.toml"
    config.write_text(CONFIG.format(dir=tmp_path))
    (tmp_path / "rig.toml").write_text(RIG)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.setblocking(False)
    env = {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM", "INVOCATION_ID")}
    env.update(NOTIFY_SOCKET=str(tmp_path / "notify.sock"), WATCHDOG_USEC=WATCHDOG_USEC)
    with open(tmp_path / "daemon.log", "wb") as log:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "host.service", "daemon", "--config", str(config),
            env=env, stderr=log,
        )  # fmt: skip
    return proc, Notifications(sock)


async def _end(proc: asyncio.subprocess.Process) -> None:
    """Make sure a process of ours is gone."""
    if proc.returncode is None:
        proc.kill()
    await proc.communicate()


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    sim = await start_sim(tmp_path)
    try:
        daemon, notes = await start_daemon(tmp_path)
    except BaseException:
        await _end(sim)
        raise
    try:
        yield Rig(sim, daemon, notes, tmp_path)
    finally:
        await _end(daemon)
        await notes.close()
        if sim.returncode is None:
            sim.send_signal(signal.SIGTERM)
        await asyncio.wait_for(sim.communicate(), 10.0)


async def test_daemon_drives_the_emulated_trolley(rig: Rig) -> None:
    ready = await rig.notes.wait_for("READY=1", 20.0)
    assert "controller link up" in ready
    assert await rig.notes.wait_for("WATCHDOG=1", 2.0)
    first = await status(rig)
    for _ in range(50):  # the link is up at the handshake; the first STATUS follows it
        if first["controller"]["state"] != "UNKNOWN":
            break
        await asyncio.sleep(0.1)
        first = await status(rig)
    assert first["link_up"] is True
    assert first["controller"]["link"] == "up"
    assert first["controller"]["state"] in ("IDLE", "READY")
    async with await connect(rig.dir / "ctl.sock") as client:
        await client.request("param_set", param="HOME_SPEED_UM_S", value=HOME_SPEED_UM_S)
        code, out = await cli(rig, "home")
        assert code == 0, out
        # Homing ends on the index pulse; a fast seek may lose a few steps on the way back.
        await wait_until_at(client, 0.0, 15.0, tol_mm=10.0)
        code, out = await cli(rig, "move", "300", "--speed", "400")
        assert code == 0, out
        await wait_until_at(client, 300.0, 10.0)
        await client.request("subscribe", topics=["pose"])
        pose = (await client.next_event(timeout_s=5))["data"]
        stats = await client.request("link_stats")
        # The pose is on the corrected track position; the raw one adds the configured home.
        assert pose["s_mm"] == pytest.approx(stats["track_s_mm"], abs=0.01)
        assert stats["raw_s_mm"] == pytest.approx(HOME_S_MM + 300.0, abs=POSITION_TOLERANCE_MM)
        assert pose["state"] == "READY"
        assert abs(pose["T_w_c"][2][3] - 4000.0) < 200.0  # the runway is 4 m up
        assert stats["handshakes"] == 1
        assert stats["frames_in"] > 100
        assert stats["homed"] is True
        assert stats["marks_seen"] >= 1  # REF_MARK over the wire into the feed
        assert "chain_scale" in stats
    shown = await status(rig)
    assert abs(shown["controller"]["position_mm"] - 300.0) < POSITION_TOLERANCE_MM
    assert shown["service"]["fps"] > 10.0  # poses published without a camera
    pings = sum(text == "WATCHDOG=1" for text in rig.notes.got)
    assert pings >= 10  # every 0.2 s (half of WATCHDOG_USEC) for the whole run
    rig.daemon.send_signal(signal.SIGTERM)
    assert await asyncio.wait_for(rig.daemon.wait(), 2.0) == 0
    await rig.notes.wait_for("STOPPING=1", 1.0)
    log = (rig.dir / "daemon.log").read_text()
    assert "controlled stop acknowledged" in log
    assert not (rig.dir / "ctl.sock").exists()


async def test_daemon_waits_for_a_missing_controller_then_connects(tmp_path: Path) -> None:
    daemon, notes = await start_daemon(tmp_path)  # no emulator yet: the pty does not exist
    sim: asyncio.subprocess.Process | None = None
    try:
        client = await connect(tmp_path / "ctl.sock")
        async with client:
            early = await client.request("status")
            assert early["link_up"] is False
            assert early["service"]["link_error"]
            sim = await start_sim(tmp_path)
            ready = await notes.wait_for("READY=1", 20.0)
            assert "controller link up" in ready
            assert (await client.request("status"))["link_up"] is True
        daemon.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(daemon.wait(), 2.0) == 0
    finally:
        await _end(daemon)
        await notes.close()
        if sim is not None:
            sim.send_signal(signal.SIGTERM)
            await asyncio.wait_for(sim.communicate(), 10.0)


async def test_bad_model_path_is_a_clear_exit_2(tmp_path: Path) -> None:
    config = tmp_path / "orbitar.toml"
    text = CONFIG.format(dir=tmp_path).replace('source = "none"', f'source = "{tmp_path}/x.avi"')
    config.write_text(text)
    (tmp_path / "rig.toml").write_text(RIG + f'[workpiece]\nmodel = "{tmp_path}/missing.obj"\n')
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.service", "daemon", "--config", str(config),
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    _, err = await asyncio.wait_for(proc.communicate(), 20.0)
    assert proc.returncode == 2
    assert "missing.obj" in err.decode()


# ---- the wiring's pieces, in process -------------------------------------------------------


def test_custom_track_rig_builds_the_same_runway() -> None:
    from host.service.wiring import build_rig, build_track
    from tests.rig.helpers import rig_config

    segments = "".join(
        f'[[track.segments]]\nkind = "straight"\nlength_mm = {length}\n'
        '[[track.segments]]\nkind = "arc"\nradius_mm = 1000.0\nangle_deg = 90.0\n'
        for length in (4000.0, 1000.0, 4000.0, 1000.0)
    )
    placement = "[track.placement]\nmatrix = [[1,0,0,0],[0,1,0,0],[0,0,1,4000],[0,0,0,1]]\n"
    custom = rig_config(segments + placement)
    track, preset = build_track(custom), build_track(Config())
    assert abs(track.length_mm - preset.length_mm) < 1e-9
    assert track.closed
    # Same shape; the custom track starts at the world origin, the preset at the runway corner.
    offset = preset.pose(0.0)[:3, 3] - track.pose(0.0)[:3, 3]
    for s_mm in (0.0, 2500.0, 7000.0, 13000.0):
        assert abs(track.pose(s_mm)[:3, 3] + offset - preset.pose(s_mm)[:3, 3]).max() < 1e-6
    rig = build_rig(custom)
    assert abs(rig.T_r_c[:3, 3] - [50.843, 47.094, 76.177]).max() < 1e-9


def test_pose_publisher_publishes_only_from_samples() -> None:
    from host.config import Config
    from host.control.api import PoseSample
    from host.service.wiring import STREAM_RATES_HZ, PosePublisher, build_pose_source

    poses, feed = build_pose_source(Config(), STREAM_RATES_HZ["serial"])
    feed.home_s_mm = 100.0
    got: list[PoseSample] = []

    class _Ctl:
        def snapshot(self) -> dict[str, Any]:
            return {"state": "MOVING"}

    publisher = PosePublisher(poses, _Ctl(), got.append, 30.0)  # type: ignore[arg-type]
    assert not publisher.publish(1_000_000_000)
    assert publisher.stale == 1
    for i in range(5):
        t_ns = 1_000_000_000 + i * 5_000_000
        feed.on_encoder(t_ns, 10.0 * i, 2000.0, 0)
        feed.on_head(t_ns, 0.0, 0.0)
    assert publisher.publish(1_000_000_000 + 25_000_000)  # 5 ms past the newest: extrapolated
    assert got[-1].state == "MOVING"
    assert abs((got[-1].s_mm or 0.0) - 150.0) < 1e-6  # 100 mm home offset + 50 mm along
    assert not publisher.publish(1_000_000_000 + 500_000_000)  # far past: stale, never a guess
    assert publisher.published == 1
