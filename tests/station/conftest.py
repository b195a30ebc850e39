"""The station under test: emulator and daemon as processes, and a headless Debian Chromium.

The emulator and the daemon (tests.hil_rig) are started once per module (they need no event
loop), and the browser once per session (tests.station.remote_browser) with fresh pages for each
test. Browser tests are skipped, saying why, only where no Chromium exists; `.ci/run` and
scripts/setup-venv.sh install Debian's chromium when they can.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
import urllib.request
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.hil_rig import HilRig, Rigs, free_port
from tests.station.remote_browser import BrowserThread

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
UI = """
[ui]
enabled = true
port = {port}
operator_token = "{operator}"
viewer_token = "{viewer}"
deadman_ms = 250.0
"""


class StationRig(HilRig):
    """The shared HIL rig with the station on a free port; restartable daemon."""

    def __init__(self, dir: Path, sections: str = "") -> None:
        self.port = free_port()
        ui = UI.format(port=self.port, operator=OPERATOR_TOKEN, viewer=VIEWER_TOKEN)
        super().__init__(dir, rig=RIG, sections=ui + sections)

    @property
    def socket(self) -> str:
        """The daemon's control socket."""
        return self.socket_path

    @property
    def base(self) -> str:
        """The station's address."""
        return f"http://127.0.0.1:{self.port}"

    def url(self, token: str = OPERATOR_TOKEN) -> str:
        """The page, with its token in the fragment (never sent to the server)."""
        return f"{self.base}/#token={token}"

    def start_daemon(self, **env: str) -> subprocess.Popen[bytes]:
        """Start the daemon and wait until the station answers."""
        daemon = super().start_daemon(**env)
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            assert daemon.poll() is None, self.log_tail()
            try:
                with urllib.request.urlopen(self.base + "/", timeout=1.0) as reply:
                    if reply.status == 200:
                        return daemon
            except OSError:
                time.sleep(0.1)
        raise TimeoutError(f"station did not answer: {self.log_tail()}")


def start_station(rigs: Rigs, sections: str = "") -> StationRig:
    """Emulator and daemon with the station (`sections`: more daemon TOML, e.g. `[bus]`)."""
    rig = rigs(StationRig, sections=sections)
    rig.start_sim()
    rig.start_daemon()
    return rig


@pytest.fixture(scope="module")
def station_rig(hil_rig_module: Rigs) -> StationRig:
    """One emulator and one daemon (with the station) for a module's tests."""
    return start_station(hil_rig_module)


def browser_missing() -> str | None:
    """Why no browser test can run here, or None."""
    try:
        import playwright.async_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (pip install -e '.[test]')"
    if not (Path(CHROMIUM).exists() or shutil.which("chromium")):
        return f"no Chromium at {CHROMIUM} (apt-get install -y chromium, as .ci/run does)"
    return None


@pytest.fixture(scope="session")
def browser_thread() -> Iterator[BrowserThread]:
    """The session's headless Debian Chromium (never a downloaded browser), on its own thread."""
    why = browser_missing()
    if why:
        pytest.skip(why)
    ARTIFACTS.mkdir(exist_ok=True)
    thread = BrowserThread(CHROMIUM, CHROMIUM_ARGS)
    try:
        yield thread
    finally:
        thread.stop()


@pytest.fixture
async def browser(browser_thread: BrowserThread) -> AsyncIterator[Any]:
    """The browser for one test: its pages are fresh contexts, all closed after the test."""
    yield browser_thread.browser()
    await browser_thread.close_contexts()


def dump(path: Path, data: Any) -> None:
    """Keep a JSON artifact beside the screenshots."""
    ARTIFACTS.mkdir(exist_ok=True)
    path.write_text(json.dumps(data, indent=2, default=str))
