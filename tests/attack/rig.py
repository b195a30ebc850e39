"""A real daemon on the emulated controller, with what an attack test checks after each attack.

Processes, not threads: `python -m tests.attack.rogue_sim` (the emulator, its truth in a file)
and `python -m host.service daemon`. `Rig.health()` is the check after every attack: the daemon
is alive, `orbitar status` answers over the Unix socket, and its memory and descriptors.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import msgpack

RIG = (
    "[track.home]\nvalue_mm = 150.0\n[track.marks]\ns_mm = [250.0, 400.0]\n[camera]\nfps = {fps}\n"
)
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
{control}
[systemd]
ready_grace_s = 30.0
status_interval_s = 0.5
{extra}
"""
START_TIMEOUT_S = 30.0


def frame(message: dict[str, Any]) -> bytes:
    """One control-socket message: u32 length, msgpack body."""
    body: bytes = msgpack.packb(message, use_bin_type=True)
    return struct.pack(">I", len(body)) + body


def read_reply(sock: socket.socket) -> dict[str, Any]:
    """The next message on a blocking socket."""
    head = recv_exactly(sock, 4)
    (length,) = struct.unpack(">I", head)
    reply: dict[str, Any] = msgpack.unpackb(recv_exactly(sock, length), raw=False)
    return reply


def recv_exactly(sock: socket.socket, n: int) -> bytes:
    """n bytes, or ConnectionError if the peer closes first."""
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError(f"closed after {len(data)} of {n} bytes")
        data += chunk
    return data


class Rig:
    """The emulator and the daemon of one attack, in `dir`."""

    def __init__(self, dir: Path, control: str = "", extra: str = "", fps: float = 20.0) -> None:
        self.dir = dir
        self.config = dir / "orbitar.toml"
        self.config.write_text(CONFIG.format(dir=dir, control=control, extra=extra))
        (Path(dir) / "rig.toml").write_text(RIG.format(fps=fps))  # CONFIG's [rig] path
        self.sim: subprocess.Popen[str] | None = None
        self.daemon: subprocess.Popen[bytes] | None = None

    @property
    def socket_path(self) -> str:
        """The daemon's control socket."""
        return str(self.dir / "ctl.sock")

    def start_sim(self) -> None:
        """The emulator behind a pty at dir/sim, once it says it is ready."""
        self.sim = subprocess.Popen(
            [sys.executable, "-m", "tests.attack.rogue_sim", "--link", "pty",
             "--link-path", str(self.dir / "sim"), "--marks", "250,400",
             "--truth", str(self.dir / "truth.json")],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        assert self.sim.stdout is not None
        while "press Ctrl-C" not in self.sim.stdout.readline():
            assert self.sim.poll() is None, "emulator exited"
        deadline = time.monotonic() + 5.0
        while not (self.dir / "truth.json").exists() and time.monotonic() < deadline:
            time.sleep(0.02)

    def start_daemon(self) -> None:
        """The daemon, its log in dir/daemon.log."""
        env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
        with open(self.dir / "daemon.log", "ab") as log:
            self.daemon = subprocess.Popen(
                [sys.executable, "-m", "host.service", "daemon", "--config", str(self.config)],
                env=env, stdout=subprocess.DEVNULL, stderr=log,
            )  # fmt: skip

    def inject(self, line: str) -> None:
        """Tell the emulator to send frames of its own (see rogue_sim)."""
        assert self.sim is not None
        assert self.sim.stdin is not None
        assert self.sim.stdout is not None
        self.sim.stdin.write(line + "\n")
        self.sim.stdin.flush()
        while "injected" not in self.sim.stdout.readline():
            assert self.sim.poll() is None

    def truth_s_mm(self) -> float:
        """The trolley's true position now (the emulator's plant, not the host's view)."""
        value: float = json.loads((self.dir / "truth.json").read_text())["s_mm"]
        return value

    def request(self, op: str, timeout_s: float = 10.0, **args: Any) -> dict[str, Any]:
        """One request on a fresh Unix connection; the reply."""
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout_s)
            sock.connect(self.socket_path)
            sock.sendall(frame({"id": 1, "op": op, "args": args}))
            return read_reply(sock)

    def wait_link_up(self, timeout_s: float = START_TIMEOUT_S) -> dict[str, Any]:
        """`status` once the controller link is up."""
        deadline = time.monotonic() + timeout_s
        last: Any = None
        while time.monotonic() < deadline:
            assert self.alive(), f"daemon exited: {self.log_tail()}"
            try:
                last = self.request("status", timeout_s=2.0)
                if last.get("ok") and last["result"]["link_up"]:
                    return dict(last["result"])
            except OSError as exc:
                last = exc
            time.sleep(0.1)
        raise AssertionError(f"link not up: {last}; log: {self.log_tail()}")

    def cli_status(self) -> tuple[int, str]:
        """`orbitar status --json` over the Unix socket, as the operator types it."""
        proc = subprocess.run(
            [sys.executable, "-m", "host.cli", "status", "--json", "--socket", self.socket_path],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        return proc.returncode, proc.stdout + proc.stderr

    def memory(self) -> tuple[int, int]:
        """(VmRSS in kB, open descriptors) of the daemon."""
        assert self.daemon is not None
        status = Path(f"/proc/{self.daemon.pid}/status").read_text()
        rss = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS"))
        return rss, len(os.listdir(f"/proc/{self.daemon.pid}/fd"))

    def alive(self) -> bool:
        """The daemon process is running."""
        return self.daemon is not None and self.daemon.poll() is None

    def log_tail(self, n: int = 3000) -> str:
        """The end of the daemon's log."""
        path = self.dir / "daemon.log"
        return path.read_text(errors="replace")[-n:] if path.exists() else ""

    def stop(self) -> None:
        """End both processes (ours, by pid)."""
        for proc in (self.daemon, self.sim):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(5.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
