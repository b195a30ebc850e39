"""Attacks on the real daemon's control socket that once succeeded (issue 14, tester's run).

The module starts the emulator and `orbitar daemon` as processes (tests.attack.rig) once; each
test attacks over the Unix socket, then checks what the operator sees: the daemon is alive,
`orbitar status` and `orbitar stop`/`estop` answer, the trolley did not move. Every attack
closes its connections and clears what it latched, so the next one finds the daemon as new.
"""

from __future__ import annotations

import socket
import struct
import time
from typing import Any

import msgpack
import pytest

from tests.attack.rig import Rig
from tests.hil_rig import Rigs, frame, read_reply

STALL_S = 1.0  # the attacked daemon's [control] stall_timeout_s
CAP = 4  # its max_unix_connections, small so the attack is quick


@pytest.fixture(scope="module")
def shared_rig(hil_rig_module: Rigs) -> Rig:
    """One emulator and daemon for the module's attacks: each attack frees what it took."""
    control = f"stall_timeout_s = {STALL_S}\nmax_unix_connections = {CAP}\nclient_buffer_kb = 256"
    rig = hil_rig_module(Rig, control=control, fps=100.0)  # events fill a stalled watcher sooner
    return rig.start()


@pytest.fixture
def rig(shared_rig: Rig) -> Rig:
    """The shared rig, as healthy as an attack must find it: daemon up, link up, no client."""
    shared_rig.wait_link_up()
    return shared_rig


def occupy(rig: Rig, op: str, **args: Any) -> socket.socket:
    """A connection in one of the cap's slots: its first request answered, not refused.

    A slot the daemon has not yet freed from an earlier connection would put this one in the
    room over the cap, where only stops are served: then it tries again.
    """
    deadline = time.monotonic() + 5.0
    while True:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(5.0)
        sock.connect(rig.socket_path)
        sock.sendall(frame({"id": 1, "op": op, "args": args}))
        if read_reply(sock)["ok"]:
            return sock
        sock.close()
        assert time.monotonic() < deadline, "no free slot"
        time.sleep(0.05)


def watcher(rig: Rig) -> socket.socket:
    """A client that subscribes to everything and then never reads."""
    sock = occupy(rig, "subscribe", topics=["pose", "state", "link"])
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    return sock


def idle_client(rig: Rig) -> socket.socket:
    """A client that asked once and then says nothing."""
    return occupy(rig, "status")


def test_estop_gets_in_while_idle_clients_fill_the_unix_socket(rig: Rig) -> None:
    # On main the next client got too_many_clients, estop included, for idle_timeout_s (600 s).
    at_mm = rig.truth_s_mm()
    socks = [idle_client(rig) for _ in range(CAP)]
    try:
        for op in ("estop", "stop"):
            code, out = rig.cli(op)
            assert code == 0, out
            assert "acked: True" in out
        code, out = rig.cli("status")
        assert code == 1, out
        assert "too_many_clients" in out  # said as it is, not "daemon not running?"
        assert "max_unix_connections" in out
        assert rig.alive()
        assert abs(rig.truth_s_mm() - at_mm) < 0.5
    finally:
        for sock in socks:
            sock.close()
    code, out = rig.cli("clear")
    assert code == 0, out


def test_watchers_that_stop_reading_are_cut_off(rig: Rig) -> None:
    # On main a watcher that never read held its slot for ever (the stall check only ran for
    # replies), so CAP of them locked `orbitar status` out for good.
    socks = [watcher(rig) for _ in range(CAP)]
    try:
        deadline = time.monotonic() + 60.0
        code, out = rig.cli("status", "--json")
        while code != 0 and time.monotonic() < deadline:
            time.sleep(1.0)
            code, out = rig.cli("status", "--json")
        assert code == 0, out
        assert '"cut_off"' in out
        assert rig.alive()
    finally:
        for sock in socks:
            sock.close()
    cuts = [line for line in rig.log_tail(20000).splitlines() if "cut off" in line]
    assert any("code=stalled" in line for line in cuts), cuts


def test_a_request_whose_id_is_too_big_to_echo_gets_one_reply(rig: Rig) -> None:
    # On main the reply, and its too_large fallback, both exceeded 64 KiB: no reply at all
    # and a traceback in the log for every such request.
    body = msgpack.packb({"id": "x" * 65500, "op": "status"})
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(10.0)
        sock.connect(rig.socket_path)
        sock.sendall(struct.pack(">I", len(body)) + body + frame({"id": 2, "op": "status"}))
        first, second = read_reply(sock), read_reply(sock)
    assert first["id"] is None
    assert first["error"]["code"] == "too_large"
    assert "id is too large" in first["error"]["message"]
    assert second["id"] == 2
    assert second["ok"]
    assert "Traceback" not in rig.log_tail(20000)
