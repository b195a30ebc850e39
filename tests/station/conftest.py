"""The station under test: emulator and daemon as processes, and a headless Debian Chromium.

The emulator and the daemon are started once per module (they need no event loop) and the
browser once per test. Browser tests are skipped, saying why, only where no Chromium exists;
`.ci/run` and scripts/setup-venv.sh install Debian's chromium when they can.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

CHROMIUM = os.environ.get("ORBITAR_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
ARTIFACTS = Path(__file__).with_name("artifacts")
OPERATOR_TOKEN = "operator-secret-0001"
VIEWER_TOKEN = "viewer-secret-00001"
MARKS = "250,400"
RIG = """
[track.home]
value_mm = 150.0
[track.marks]
s_mm = [250.0, 400.0]
[head]
tilt_max_deg = 80.0
[camera]
fps = 20.0
width = 1280
height = 1024
[camera.intrinsics]
u0 = 640.0
v0 = 512.0
fx = 1400.0
fy = 1400.0
[workpiece.frame]
matrix = [[1, 0, 0, -300.0], [0, 1, 0, -300.0], [0, 0, 1, 0], [0, 0, 0, 1]]
"""
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
[ui]
enabled = true
port = {port}
operator_token = "{operator}"
viewer_token = "{viewer}"
deadman_ms = 250.0
"""


def free_port() -> int:
    """A TCP port on 127.0.0.1 nobody listens on now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class StationRig:
    """Emulator + daemon with the station; restartable daemon."""

    dir: Path
    port: int
    sim: subprocess.Popen[bytes]
    daemon: subprocess.Popen[bytes] | None = None
    logs: list[Path] = field(default_factory=list)
    extra_config: str = ""  # more TOML for the daemon (e.g. a [bus] section)

    @property
    def socket(self) -> str:
        """The daemon's control socket."""
        return str(self.dir / "ctl.sock")

    @property
    def base(self) -> str:
        """The station's address."""
        return f"http://127.0.0.1:{self.port}"

    def url(self, token: str = OPERATOR_TOKEN) -> str:
        """The page, with its token in the fragment (never sent to the server)."""
        return f"{self.base}/#token={token}"

    def start_daemon(self) -> None:
        """Start the daemon and wait until the station answers."""
        config = self.dir / "orbitar.toml"
        text = CONFIG.format(
            dir=self.dir, port=self.port, operator=OPERATOR_TOKEN, viewer=VIEWER_TOKEN
        )
        config.write_text(text + self.extra_config)
        (self.dir / "rig.toml").write_text(RIG)  # the rig file CONFIG's [rig] path names
        env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
        log = self.dir / f"daemon-{len(self.logs)}.log"
        self.logs.append(log)
        with open(log, "wb") as out:
            self.daemon = subprocess.Popen(
                [sys.executable, "-m", "host.service", "daemon", "--config", str(config)],
                env=env,
                stderr=out,
            )
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            assert self.daemon.poll() is None, log.read_text()
            try:
                with urllib.request.urlopen(self.base + "/", timeout=1.0) as reply:
                    if reply.status == 200:
                        return
            except OSError:
                time.sleep(0.1)
        raise TimeoutError(f"station did not answer: {log.read_text()}")

    def stop_daemon(self) -> None:
        """SIGTERM the daemon and wait for its exit."""
        if self.daemon is not None and self.daemon.poll() is None:
            self.daemon.send_signal(signal.SIGTERM)
            try:
                self.daemon.wait(10.0)
            except subprocess.TimeoutExpired:
                self.daemon.kill()
                self.daemon.wait()
        self.daemon = None


def _start_sim(directory: Path) -> subprocess.Popen[bytes]:
    """The emulator behind a pty at dir/sim, once it says it is ready."""
    link = str(directory / "sim")
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil_sim", "--link", "pty", "--link-path", link, "--marks", MARKS],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
    )
    assert proc.stdout is not None
    deadline = time.monotonic() + 20.0
    seen = b""
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        if ready:
            seen += os.read(proc.stdout.fileno(), 4096)
        if b"press Ctrl-C" in seen:
            return proc
        assert proc.poll() is None, "the emulator exited"
    proc.kill()
    raise TimeoutError("the emulator did not start")


@pytest.fixture(scope="module")
def station_rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[StationRig]:
    """One emulator and one daemon (with the station) for a module's tests."""
    directory = tmp_path_factory.mktemp("station")
    sim = _start_sim(directory)
    rig = StationRig(directory, free_port(), sim)
    try:
        rig.start_daemon()
        yield rig
    finally:
        rig.stop_daemon()
        sim.send_signal(signal.SIGTERM)
        try:
            sim.wait(10.0)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()


def browser_missing() -> str | None:
    """Why no browser test can run here, or None."""
    try:
        import playwright.async_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[test]')"
    if not (Path(CHROMIUM).exists() or shutil.which("chromium")):
        return f"no Chromium at {CHROMIUM} (apt-get install -y chromium, as .ci/run does)"
    return None


@pytest.fixture
async def browser() -> AsyncIterator[Any]:
    """A headless Debian Chromium (never a downloaded browser)."""
    why = browser_missing()
    if why:
        pytest.skip(why)
    from playwright.async_api import async_playwright

    ARTIFACTS.mkdir(exist_ok=True)
    async with async_playwright() as pw:
        chromium = await pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            await chromium.close()


def dump(path: Path, data: Any) -> None:
    """Keep a JSON artifact beside the screenshots."""
    ARTIFACTS.mkdir(exist_ok=True)
    path.write_text(json.dumps(data, indent=2, default=str))
