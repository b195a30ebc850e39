"""sd_notify over a Unix datagram socket, and the watchdog pinged from the event loop."""

from __future__ import annotations

import asyncio
import itertools
import os
import socket
import time
import uuid
from pathlib import Path

from host.config import Config, ControlConfig, RecordingConfig, SystemdConfig
from host.recording import RecordingReader
from host.service.daemon import Daemon
from host.service.notify import Notifier
from tests.fakes import MemoryController, MemoryFrameLoop


def test_no_socket_means_no_op() -> None:
    notifier = Notifier({})
    assert not notifier.enabled
    assert notifier.ready("x") is False
    assert notifier.watchdog_interval_s is None


def test_path_socket_receives_fields(tmp_path: Path) -> None:
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(tmp_path / "n.sock"))
        notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "n.sock")})
        assert notifier.ready("link up")
        notifier.close()
        assert sock.recv(100) == b"READY=1\nSTATUS=link up"


def test_abstract_socket(tmp_path: Path) -> None:
    name = f"orbitar-test-{uuid.uuid4().hex}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(b"\0" + name.encode())
        notifier = Notifier({"NOTIFY_SOCKET": "@" + name})
        assert notifier.stopping()
        notifier.close()
        assert sock.recv(100) == b"STOPPING=1\nSTATUS=stopping"


def test_send_failure_is_counted_not_raised(tmp_path: Path) -> None:
    notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody.sock")})
    assert notifier.watchdog() is False
    assert notifier.errors == 1
    notifier.close()


def test_a_manager_that_stops_reading_never_blocks_us(tmp_path: Path) -> None:
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(tmp_path / "n.sock"))
        notifier = Notifier({"NOTIFY_SOCKET": str(tmp_path / "n.sock")})
        results = [notifier.watchdog() for _ in range(200)]  # nobody reads: the queue fills
        notifier.close()
    assert results[0] is True
    assert results[-1] is False
    assert notifier.errors == results.count(False)


def test_watchdog_period_and_pid() -> None:
    assert Notifier({"WATCHDOG_USEC": "10000000"}).watchdog_interval_s == 5.0
    other_pid = {"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": str(os.getpid() + 1)}
    assert Notifier(other_pid).watchdog_interval_s is None
    assert Notifier({"WATCHDOG_USEC": "junk"}).watchdog_interval_s is None


async def test_stalled_loop_stops_pinging_and_poses_are_recorded(tmp_path: Path) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "n.sock"))
    sock.setblocking(False)
    env = {"NOTIFY_SOCKET": str(tmp_path / "n.sock"), "WATCHDOG_USEC": "100000"}
    config = Config(
        control=ControlConfig(socket_path=str(tmp_path / "c.sock")),
        systemd=SystemdConfig(ready_grace_s=60.0),
        recording=RecordingConfig(enabled=True, dir=str(tmp_path)),
    )
    fake = MemoryController()
    daemon = Daemon(
        config,
        lambda cfg, tap: fake,
        lambda cfg, ctl, sink, tap: MemoryFrameLoop(fake, sink, fps=50.0),
        notifier=Notifier(env),
    )
    task = asyncio.create_task(daemon.run())
    loop = asyncio.get_running_loop()
    pings: list[float] = []
    try:
        while len(pings) < 3:
            if await loop.sock_recv(sock, 100) == b"WATCHDOG=1":
                pings.append(time.monotonic())
        time.sleep(0.5)  # the event loop is stuck: no ping may go out meanwhile
        stalled_at = time.monotonic()
        while len(pings) < 5:
            if await loop.sock_recv(sock, 100) == b"WATCHDOG=1":
                pings.append(time.monotonic())
    finally:
        daemon.request_stop()
        assert await task == 0
        sock.close()
    gaps = [b - a for a, b in itertools.pairwise(pings)]
    assert max(gaps) >= 0.45  # the stall shows as a gap: systemd would have noticed
    assert pings[3] >= stalled_at - 0.01
    assert fake.calls[-2:] == [("stop", ()), ("close", ())]
    poses = [r for r in RecordingReader([tmp_path]) if r.kind == "pose"]
    assert poses
    assert poses[-1].data["T_w_c"][2][3] == 4000.0
