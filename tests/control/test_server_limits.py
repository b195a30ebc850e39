"""Nothing a client does exhausts the daemon: floods of requests and of idle connections.

The server runs in a process of its own (tests/control/server_process.py) so that its resident
memory and its file descriptors are measured alone. Every flood is bounded in bytes and time.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import select
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import pytest

from host.control.server import BACKLOG
from host.control.wire import pack
from tests.control.server_process import fd_count, rss_kb

ROOT = Path(__file__).resolve().parents[2]
TOKEN = "operator-secret-0123456789"
MAX_TCP = 20
MAX_UNIX = 6
FLOOD_BYTES = 24 * 1024 * 1024  # what a non-reading client may try to push in
FLOOD_S = 20.0  # an upper bound: the server cuts the flood off within ~2 s
NOFILE = 128  # the server's open-file limit: far below the idle flood, as systemd's 1024 was
RSS_GROWTH_MAX_KB = 25 * 1024  # a few client buffers; the unbounded server grew by hundreds of MB


@dataclass
class ServerProcess:
    """The running server: its pid, socket path, TCP port and stderr file."""

    proc: subprocess.Popen[bytes]
    pid: int
    path: str
    tcp_port: int
    stderr: Path


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    tmp = tmp_path_factory.mktemp("limits")
    path = str(tmp / "ctl.sock")
    fields = {
        "socket_path": path,
        "tcp_enabled": True,
        "tcp_port": 0,
        "operator_token": TOKEN,
        "max_tcp_connections": MAX_TCP,
        "max_unix_connections": MAX_UNIX,
        "hello_timeout_s": 1.5,
        "idle_timeout_s": 60.0,
        "stall_timeout_s": 1.5,
        "client_buffer_kb": 1024,
    }
    stderr = tmp / "server.log"
    with stderr.open("wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tests.control.server_process", json.dumps(fields)],
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=err,
            preexec_fn=_limit_files,
        )
    assert proc.stdout is not None
    assert proc.stdin is not None
    line = proc.stdout.readline()
    assert line, f"server did not start: {stderr.read_text()}"
    info = json.loads(line)
    yield ServerProcess(proc, info["pid"], path, info["tcp_port"], stderr)
    proc.stdin.close()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _limit_files() -> None:
    """In the child: an open-file limit the idle flood would exceed without the caps."""
    resource.setrlimit(
        resource.RLIMIT_NOFILE, (NOFILE, resource.getrlimit(resource.RLIMIT_NOFILE)[1])
    )


def _read_message(sock: socket.socket) -> dict[str, Any]:
    """One framed reply from a blocking socket."""
    (n,) = struct.unpack(">I", sock.recv(4, socket.MSG_WAITALL))
    reply: dict[str, Any] = msgpack.unpackb(sock.recv(n, socket.MSG_WAITALL))
    return reply


def _unix_status(path: str, timeout_s: float = 3.0) -> dict[str, Any]:
    """The operator's `status` over the Unix socket, blocking, within `timeout_s`."""
    with socket.socket(socket.AF_UNIX) as sock:
        sock.settimeout(timeout_s)
        sock.connect(path)
        sock.sendall(pack({"id": 1, "op": "status", "args": {}}))
        return _read_message(sock)


def _connect(server: ServerProcess, listener: str) -> socket.socket:
    """A raw client socket on one listener."""
    family = socket.AF_UNIX if listener == "unix" else socket.AF_INET
    sock = socket.socket(family)
    for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):  # small kernel buffers fill at once
        sock.setsockopt(socket.SOL_SOCKET, option, 32 * 1024)
    sock.settimeout(5)
    sock.connect(server.path if listener == "unix" else ("127.0.0.1", server.tcp_port))
    return sock


def _flood(sock: socket.socket, pid: int) -> tuple[int, int, bool]:
    """Send `status` requests and never read: (bytes sent, peak server RSS kB, cut off?)."""
    chunk = b"".join(pack({"id": i, "op": "status"}) for i in range(2000))
    sock.setblocking(False)
    sent, peak, offset = 0, rss_kb(pid), 0
    deadline = time.monotonic() + FLOOD_S
    while sent < FLOOD_BYTES and time.monotonic() < deadline:
        try:
            n = sock.send(chunk[offset:])
        except BlockingIOError:
            select.select([], [sock], [], 0.05)
            n = 0
        except (BrokenPipeError, ConnectionResetError):
            return sent, max(peak, rss_kb(pid)), True
        sent += n
        offset = (offset + n) % len(chunk)
        peak = max(peak, rss_kb(pid))
    return sent, peak, False


@pytest.mark.parametrize("listener", ["unix", "tcp"])
def test_a_client_that_never_reads_cannot_grow_the_daemon(
    server: ServerProcess, listener: str
) -> None:
    before_kb = rss_kb(server.pid)
    with _connect(server, listener) as sock:  # on TCP nothing but requests before any hello
        sent, peak_kb, cut = _flood(sock, server.pid)
    growth_kb = peak_kb - before_kb
    assert growth_kb < RSS_GROWTH_MAX_KB, f"{growth_kb} kB more after {sent} bytes of requests"
    assert cut, f"still connected after {sent} bytes sent and {FLOOD_S} s of unread replies"
    assert _unix_status(server.path)["ok"] is True  # the daemon serves the next client


def test_idle_connection_flood_leaves_the_operator_a_way_in(server: ServerProcess) -> None:
    base_fds = fd_count(server.pid)
    log_before = server.stderr.stat().st_size
    idle = [socket.socket() for _ in range(300)]
    try:
        for sock in idle:  # all at once, as a flood would: connects complete as the server accepts
            sock.setblocking(False)
            sock.connect_ex(("127.0.0.1", server.tcp_port))
        time.sleep(0.5)
        assert fd_count(server.pid) <= base_fds + MAX_TCP + BACKLOG + 4
        status = _unix_status(server.path)
        assert status["ok"] is True
        assert status["result"]["link_up"] is False
        codes = _first_messages(idle, {"too_many_clients", "timeout"}, within_s=6.0)
        assert "control.max_tcp_connections" in codes["too_many_clients"]
        assert "control.hello_timeout_s" in codes["timeout"]  # admitted, never said hello
        assert fd_count(server.pid) <= base_fds + MAX_TCP + BACKLOG + 4
        counters = _unix_status(server.path)["result"]["control"]
        assert counters["refused"] > 0
        assert counters["cut_off"] > 0
    finally:
        for sock in idle:
            sock.close()
    assert _fds_fall_to(server.pid, base_fds + 2, within_s=5.0)
    log = server.stderr.read_bytes()[log_before:]
    assert b"Traceback" not in log
    assert log.count(b"\n") < 20, log.decode()[-2000:]  # 300 refusals, a few throttled lines


def _first_messages(socks: list[socket.socket], codes: set[str], within_s: float) -> dict[str, str]:
    """Error code → message of the first message seen with each code, on any of `socks`."""
    found: dict[str, str] = {}
    waiting = list(socks)
    deadline = time.monotonic() + within_s
    while set(found) != codes and time.monotonic() < deadline:
        readable, _, _ = select.select(waiting, [], [], 0.1)
        for sock in readable:
            waiting.remove(sock)
            sock.settimeout(1.0)
            with contextlib.suppress(OSError, struct.error):
                error = _read_message(sock)["error"]
                found.setdefault(error["code"], error["message"])
    assert set(found) == codes, found
    return found


def _fds_fall_to(pid: int, limit: int, within_s: float) -> bool:
    """Wait until the process has at most `limit` descriptors open."""
    deadline = time.monotonic() + within_s
    while fd_count(pid) > limit:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_failed_hellos_are_limited_per_connection(server: ServerProcess) -> None:
    with _connect(server, "tcp") as sock:
        sock.settimeout(5)
        for i in range(3):
            sock.sendall(pack({"id": i, "op": "hello", "args": {"token": "guess"}}))
        replies = [_read_message(sock) for _ in range(4)]
        assert [r["error"]["code"] for r in replies] == ["unauthorized"] * 4
        assert "too many failed hellos" in replies[3]["error"]["message"]
        assert sock.recv(1) == b""  # closed by the server
