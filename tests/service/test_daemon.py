"""The daemon as systemd runs it: a subprocess, a fake NOTIFY_SOCKET, signals, control socket."""

from __future__ import annotations

import asyncio
import itertools
import os
import signal
import socket
import sys
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from host.control.client import ControlClient
from host.outputs.freed import decode_d1
from host.service.lock import EXIT_ALREADY_RUNNING

CONFIG = """
[control]
socket_path = "{dir}/ctl.sock"
[outputs.freed]
enabled = true
destinations = ["127.0.0.1:{freed_port}"]
camera_id = 3
[recording]
enabled = true
dir = "{dir}/rec"
[systemd]
ready_grace_s = {grace}
status_interval_s = 0.2
[log]
level = "info"
"""


@dataclass
class Notifications:
    """Datagrams the daemon sent to our NOTIFY_SOCKET, with arrival times."""

    sock: socket.socket
    got: list[tuple[float, str]] = field(default_factory=list)

    async def wait_for(self, needle: str, timeout_s: float = 10.0) -> str:
        """The first notification containing `needle` (already received or arriving)."""
        for _, text in self.got:
            if needle in text:
                return text
        loop = asyncio.get_running_loop()
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            data = await asyncio.wait_for(loop.sock_recv(self.sock, 4096), left)
            self.got.append((time.monotonic(), data.decode()))
            if needle in self.got[-1][1]:
                return self.got[-1][1]
        raise TimeoutError(needle)


class Freed(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.packets: asyncio.Queue[bytes] = asyncio.Queue()

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.packets.put_nowait(data)


@dataclass
class Running:
    proc: asyncio.subprocess.Process
    notes: Notifications
    freed: Freed
    dir: Path
    config: Path

    async def stderr_text(self) -> str:
        """What the daemon logged (a file, so a chatty daemon can never block on a full pipe)."""
        return (self.dir / "stderr.log").read_text()


FAKE_DAEMON = (sys.executable, "-m", "tests.service.fake_daemon")


async def start_daemon(
    tmp_path: Path,
    unreachable: bool = False,
    grace: float = 30.0,
    extra_env: dict[str, str] | None = None,
) -> tuple[Running, asyncio.DatagramTransport]:
    """The daemon in a subprocess, with a notify socket and a FreeD receiver of our own."""
    loop = asyncio.get_running_loop()
    transport, freed = await loop.create_datagram_endpoint(Freed, local_addr=("127.0.0.1", 0))
    port = transport.get_extra_info("sockname")[1]
    config = tmp_path / "orbitar.toml"
    config.write_text(CONFIG.format(dir=tmp_path, freed_port=port, grace=grace))
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.setblocking(False)
    env = {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM", "INVOCATION_ID")}
    env.update(NOTIFY_SOCKET=str(tmp_path / "notify.sock"), WATCHDOG_USEC="400000")
    env.update(extra_env or {})
    flags = ["--unreachable"] if unreachable else []
    with open(tmp_path / "stderr.log", "wb") as stderr:
        proc = await asyncio.create_subprocess_exec(
            *FAKE_DAEMON, *flags, "daemon", "--config", str(config), env=env, stderr=stderr,
        )  # fmt: skip
    return Running(proc, Notifications(sock), freed, tmp_path, config), transport


@pytest.fixture
async def daemon(tmp_path: Path) -> AsyncIterator[Running]:
    running, transport = await start_daemon(tmp_path)
    try:
        yield running
    finally:
        if running.proc.returncode is None:
            running.proc.kill()
            await running.proc.wait()
        running.notes.sock.close()
        transport.close()


async def connect(path: Path) -> ControlClient:
    """Connect once the daemon has created its socket."""
    for _ in range(200):
        if path.exists():
            try:
                return await ControlClient.connect_unix(str(path))
            except ConnectionRefusedError:
                pass
        await asyncio.sleep(0.05)
    raise TimeoutError(path)


async def test_ready_status_watchdog_outputs_and_sigterm(daemon: Running) -> None:
    ready = await daemon.notes.wait_for("READY=1")
    assert "link up" in ready
    await daemon.notes.wait_for("fps")  # a periodic STATUS= line with the frame rate
    first = await daemon.notes.wait_for("WATCHDOG=1")
    assert first
    async with await connect(daemon.dir / "ctl.sock") as client:
        status = await client.request("status")
        assert status["link_up"] is True
        calibration = await client.request("calibration")
        assert calibration["intrinsics"]["fx"] == 3676.462  # Table 1, from the config
        assert calibration["m_cr"][0][3] == 50.843
        await client.request("home")
        await client.request("move", position_mm=250.0, speed_mm_s=1000.0)
        await client.request("subscribe", topics=["pose"])
        event = await client.next_event(timeout_s=10)
        assert event["topic"] == "pose"
        assert event["data"]["T_w_c"][2][3] == 4000.0
    packet = decode_d1(await asyncio.wait_for(daemon.freed.packets.get(), 10))
    assert packet.camera_id == 3
    assert packet.pose.z_mm == 4000.0
    async with await connect(daemon.dir / "ctl.sock") as client:
        status = await client.request("status")
        assert status["service"]["freed"]["sent"] >= 1  # the packet we just received was counted
    pings = [t for t, text in daemon.notes.got if "WATCHDOG=1" in text]
    assert len(pings) >= 1
    daemon.proc.send_signal(signal.SIGTERM)
    assert await asyncio.wait_for(daemon.proc.wait(), 2.0) == 0
    await daemon.notes.wait_for("STOPPING=1", 2.0)
    log = await daemon.stderr_text()
    assert "controlled stop acknowledged" in log
    assert list((daemon.dir / "rec").glob("*.orec"))
    assert not (daemon.dir / "ctl.sock").exists()


async def test_watchdog_pings_at_half_the_period(daemon: Running) -> None:
    await daemon.notes.wait_for("READY=1")
    loop = asyncio.get_running_loop()
    for _ in range(8):
        data = await asyncio.wait_for(loop.sock_recv(daemon.notes.sock, 4096), 5)
        daemon.notes.got.append((time.monotonic(), data.decode()))
    pings = [t for t, text in daemon.notes.got if text == "WATCHDOG=1"]
    gaps = [b - a for a, b in itertools.pairwise(pings)]
    assert gaps, daemon.notes.got
    assert max(gaps) < 0.4  # WATCHDOG_USEC=0.4 s: pings must come well within it
    daemon.proc.send_signal(signal.SIGTERM)
    assert await asyncio.wait_for(daemon.proc.wait(), 5) == 0


async def test_sighup_applies_what_it_can_and_names_the_rest(daemon: Running) -> None:
    await daemon.notes.wait_for("READY=1")
    text = daemon.config.read_text().replace('level = "info"', 'level = "debug"')
    text = text.replace("enabled = true\ndestinations", "enabled = false\ndestinations")
    daemon.config.write_text(text + '\n[link]\nurl = "/dev/ttyACM7"\n')
    daemon.proc.send_signal(signal.SIGHUP)
    await asyncio.sleep(1.0)
    daemon.proc.send_signal(signal.SIGTERM)
    assert await asyncio.wait_for(daemon.proc.wait(), 5) == 0
    log = await daemon.stderr_text()
    assert "reloaded applied=log,outputs" in log
    assert "changes need a restart sections=link" in log


async def test_bad_reload_keeps_running(daemon: Running) -> None:
    await daemon.notes.wait_for("READY=1")
    daemon.config.write_text("[link]\nbaud = -1\n")
    daemon.proc.send_signal(signal.SIGHUP)
    await asyncio.sleep(0.5)
    assert daemon.proc.returncode is None
    daemon.proc.send_signal(signal.SIGTERM)
    assert await asyncio.wait_for(daemon.proc.wait(), 5) == 0
    assert "link.baud = -1" in await daemon.stderr_text()


async def test_ready_after_grace_says_why_without_link(tmp_path: Path) -> None:
    running, transport = await start_daemon(
        tmp_path, unreachable=True, grace=0.3, extra_env={"INVOCATION_ID": "x"}
    )
    try:
        ready = await running.notes.wait_for("READY=1")
        assert "running without controller" in ready
        assert "no device" in ready
        running.proc.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(running.proc.wait(), 5) == 0
        log = await running.stderr_text()
        assert "<4>host.service.daemon: controller not reachable" in log  # journald form
    finally:
        if running.proc.returncode is None:
            running.proc.kill()
            await running.proc.wait()
        running.notes.sock.close()
        transport.close()


async def test_invalid_config_exits_2_with_every_problem(tmp_path: Path) -> None:
    config = tmp_path / "bad.toml"
    config.write_text('[link]\nkind = "pigeon"\n[camera]\nsource = -1\n')
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.service", "daemon", "--config", str(config),
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    _, err = await proc.communicate()
    assert proc.returncode == 2
    assert b"link.kind = 'pigeon'" in err
    assert b"camera.source = -1" in err


async def test_bad_rig_file_exits_2_naming_its_key(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text("[camera]\nfps = 0\n")
    config = tmp_path / "orbitar.toml"
    config.write_text(f'[rig]\npath = "{rig}"\n')
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.service", "daemon", "--config", str(config),
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    _, err = await proc.communicate()
    assert proc.returncode == 2
    assert b"rig.toml: camera.fps = 0: out of range" in err


async def test_second_daemon_refuses_and_leaves_the_first_alone(daemon: Running) -> None:
    await daemon.notes.wait_for("READY=1")
    socket_path = daemon.dir / "ctl.sock"
    second = await asyncio.create_subprocess_exec(
        *FAKE_DAEMON, "daemon", "--config", str(daemon.config), stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    _, err = await asyncio.wait_for(second.communicate(), 20.0)
    assert second.returncode == EXIT_ALREADY_RUNNING
    assert f"pid {daemon.proc.pid}" in err.decode()
    assert "exits without touching it" in err.decode()
    assert socket_path.exists()  # the running daemon's socket is still there, and answers
    async with await connect(socket_path) as client:
        assert (await client.request("status"))["service"]["phase"] == "running"
    daemon.proc.send_signal(signal.SIGTERM)
    assert await asyncio.wait_for(daemon.proc.wait(), 5) == 0
