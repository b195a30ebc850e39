"""The HIL rig of the process-level tests: the emulator behind a pty, and the real daemon.

The emulator (`python -m hil_sim`, or a module that extends it such as tests.attack.rogue_sim)
serves the firmware mirror and the simulated plant on a pty at DIR/sim; `python -m host.service
daemon` reaches it through the serial link of DIR/orbitar.toml, with DIR/rig.toml as its rig
file and DIR/ctl.sock as its control socket. Both are processes of ours, ended by pid.

The fixtures `hil_rig` (one test) and `hil_rig_module` (shared by a module's tests), in
tests/conftest.py, are `Rigs` (`rigs_in`): they hand out rigs, each in a directory of its own,
and stop every process those started afterwards.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Self, TypeVar, overload

import msgpack

HOME_S_MM = 150.0  # the emulator's home switch, as the rig file has it
MARKS = "250,400"  # the emulator's reference marks, as the rig file has them
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 10.0
# Variables a supervisor may have set for the test run itself: never the daemon's.
SUPERVISOR_ENV = ("NOTIFY_SOCKET", "WATCHDOG_USEC", "JOURNAL_STREAM", "INVOCATION_ID")

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
{sections}
"""


def rig_toml(fps: float = 20.0) -> str:
    """The rig file: the emulator's home and marks; without a camera, `fps` poses a second."""
    return RIG.format(fps=fps)


def daemon_config(directory: Path, control: str = "", sections: str = "") -> str:
    """The daemon's TOML: the emulator's pty, the rig file, a private control socket.

    `control` adds lines to `[control]`; `sections` adds tables (`[recording]`, `[ui]`, …).
    """
    return CONFIG.format(dir=directory, control=control, sections=sections)


def free_port() -> int:
    """A TCP port on 127.0.0.1 nothing listens on right now."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def frame(message: dict[str, Any]) -> bytes:
    """One control-socket message: u32 length, msgpack body."""
    body: bytes = msgpack.packb(message, use_bin_type=True)
    return struct.pack(">I", len(body)) + body


def read_reply(sock: socket.socket) -> dict[str, Any]:
    """The next message on a blocking socket."""
    (length,) = struct.unpack(">I", recv_exactly(sock, 4))
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


def request(socket_path: str, op: str, timeout_s: float = 10.0, **args: Any) -> dict[str, Any]:
    """One request on a fresh blocking Unix connection; the whole reply."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(socket_path)
        sock.sendall(frame({"id": 1, "op": op, "args": args}))
        return read_reply(sock)


class HilRig:
    """The emulator and the daemon of one rig, in `dir`; the daemon can be restarted."""

    sim_module = "hil_sim"

    def __init__(
        self,
        dir: Path,
        *,
        fps: float = 20.0,
        rig: str | None = None,
        control: str = "",
        sections: str = "",
    ) -> None:
        self.dir = dir
        self.config = dir / "orbitar.toml"
        self.rig_path = dir / "rig.toml"  # the config's [rig] path
        self.write_config(control, sections)
        self.rig_path.write_text(rig if rig is not None else rig_toml(fps))
        self.sim: subprocess.Popen[bytes] | None = None
        self.daemon: subprocess.Popen[bytes] | None = None
        self.logs: list[Path] = []  # the daemon's stderr, one file per start
        self._said = b""  # what the emulator printed and no wait has consumed yet

    def write_config(self, control: str = "", sections: str = "") -> None:
        """(Re)write the daemon's config (a SIGHUP makes a running daemon read it)."""
        self.config.write_text(daemon_config(self.dir, control, sections))

    @property
    def socket_path(self) -> str:
        """The daemon's control socket."""
        return str(self.dir / "ctl.sock")

    def sim_args(self) -> list[str]:
        """The emulator's command line after `python -m MODULE`."""
        return ["--link", "pty", "--link-path", str(self.dir / "sim"), "--marks", MARKS]

    def start_sim(self, timeout_s: float = 20.0) -> None:
        """The emulator behind a pty at dir/sim, once it says it is ready."""
        with open(self.dir / "sim.log", "ab") as log:
            self.sim = subprocess.Popen(
                [sys.executable, "-m", self.sim_module, *self.sim_args()],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log,
            )  # fmt: skip
        self.wait_sim_says(b"press Ctrl-C", timeout_s)

    def wait_sim_says(self, needle: bytes, timeout_s: float) -> None:
        """Read the emulator's stdout until `needle`; consume it and what came before."""
        assert self.sim is not None
        assert self.sim.stdout is not None
        deadline = time.monotonic() + timeout_s
        while needle not in self._said:
            assert self.sim.poll() is None, f"the emulator exited: {self._said[-500:]!r}"
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"the emulator did not say {needle!r}: {self._said[-500:]!r}")
            ready, _, _ = select.select([self.sim.stdout], [], [], min(left, 0.5))
            if ready:
                self._said += os.read(self.sim.stdout.fileno(), 4096)
        self._said = self._said.split(needle, 1)[1]

    def tell_sim(self, line: str) -> None:
        """A line on the emulator's stdin."""
        assert self.sim is not None
        assert self.sim.stdin is not None
        self.sim.stdin.write(line.encode() + b"\n")
        self.sim.stdin.flush()

    def start_daemon(self, **env: str) -> subprocess.Popen[bytes]:
        """The daemon on this config, its stderr in a log of its own; `env` adds variables."""
        environment = {k: v for k, v in os.environ.items() if k not in SUPERVISOR_ENV}
        environment.update(env)
        log = self.dir / ("daemon.log" if not self.logs else f"daemon-{len(self.logs)}.log")
        self.logs.append(log)
        with open(log, "ab") as out:
            self.daemon = subprocess.Popen(
                [sys.executable, "-m", "host.service", "daemon", "--config", str(self.config)],
                env=environment, stdout=subprocess.DEVNULL, stderr=out,
            )  # fmt: skip
        return self.daemon

    async def start_daemon_notified(self, **env: str) -> Notifications:
        """The daemon with a NOTIFY_SOCKET of ours, drained while the event loop runs."""
        notes = Notifications(self.dir / "notify.sock")
        self.start_daemon(NOTIFY_SOCKET=str(notes.path), **env)
        return notes

    def start(self) -> Self:
        """Emulator, then daemon, until the controller link is up."""
        self.start_sim()
        self.start_daemon()
        self.wait_link_up()
        return self

    def request(self, op: str, timeout_s: float = 10.0, **args: Any) -> dict[str, Any]:
        """One request to the daemon on a fresh blocking Unix connection; the whole reply."""
        return request(self.socket_path, op, timeout_s, **args)

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

    def cli(self, *args: str, timeout_s: float = 30.0) -> tuple[int, str]:
        """`orbitar ARGS --socket …` as an operator types it; (exit code, stdout + stderr)."""
        proc = subprocess.run(
            [sys.executable, "-m", "host.cli", *args, "--socket", self.socket_path],
            capture_output=True, text=True, timeout=timeout_s,
        )  # fmt: skip
        return proc.returncode, proc.stdout + proc.stderr

    async def daemon_exit(self, timeout_s: float) -> int:
        """The daemon's exit code, waited for without blocking the event loop."""
        assert self.daemon is not None
        return await asyncio.to_thread(self.daemon.wait, timeout_s)

    def alive(self) -> bool:
        """The daemon process is running."""
        return self.daemon is not None and self.daemon.poll() is None

    def log_tail(self, n: int = 3000) -> str:
        """The end of the newest daemon log."""
        if not self.logs or not self.logs[-1].exists():
            return ""
        return self.logs[-1].read_text(errors="replace")[-n:]

    def stop_daemon(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """SIGTERM the daemon (a controlled stop) and wait; SIGKILL if it hangs."""
        _end(self.daemon, timeout_s)
        self.daemon = None

    def stop(self) -> None:
        """End both processes (ours, by pid), the daemon first."""
        self.stop_daemon()
        _end(self.sim, STOP_TIMEOUT_S)
        if self.sim is not None:
            for pipe in (self.sim.stdin, self.sim.stdout):
                if pipe is not None:
                    with contextlib.suppress(OSError):
                        pipe.close()


def _end(proc: subprocess.Popen[bytes] | None, timeout_s: float) -> None:
    """SIGTERM a process of ours and wait for it; SIGKILL if it does not go."""
    if proc is None or proc.poll() is not None:
        return
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class Notifications:
    """Our NOTIFY_SOCKET for the daemon, drained in the background (its queue is ~10 deep)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)
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


R = TypeVar("R", bound=HilRig)


class Rigs:
    """Makes rigs in fresh directories; stops all of them at the fixture's end."""

    def __init__(self, directory: Callable[[], Path]) -> None:
        self._directory = directory
        self._made: list[HilRig] = []

    @overload
    def __call__(self, **options: Any) -> HilRig: ...

    @overload
    def __call__(self, kind: type[R], **options: Any) -> R: ...

    def __call__(self, kind: type[HilRig] = HilRig, **options: Any) -> HilRig:
        """A rig of `kind` (HilRig or a subclass), not yet started; options go to its init."""
        rig = kind(self._directory(), **options)
        self._made.append(rig)
        return rig

    def stop(self) -> None:
        """End every process of every rig made here."""
        for rig in reversed(self._made):
            rig.stop()


@contextlib.contextmanager
def rigs_in(tmp_path_factory: Any) -> Iterator[Rigs]:
    """Rigs in pytest's short temporary directories (a Unix socket's path has at most 107
    bytes), their processes ended on leaving: the body of every rig fixture."""
    rigs = Rigs(lambda: Path(tmp_path_factory.mktemp("hil")))
    try:
        yield rigs
    finally:
        rigs.stop()
