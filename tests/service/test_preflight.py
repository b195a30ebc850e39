"""`config check`, the daemon's start and SIGHUP apply the same checks, and name the key."""

from __future__ import annotations

import asyncio
import os
import signal
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from host.cli import main as cli_main
from host.config import loads_config
from host.service.preflight import UNIX_PATH_MAX_BYTES, preflight
from tests.service.test_daemon import Running, connect, start_daemon

TOKEN = "t" * 32
LONG_DIR = "/tmp/" + "d" * 120

# Files that `config check` used to pass and the daemon then refused (or crashed on).
START_FAILURES = {
    "missing rig file": ('[rig]\npath = "/nonexistent/rig.toml"\n', "rig.path = '/nonexistent/"),
    "unresolvable tcp host": (
        f'[control]\ntcp_enabled = true\ntcp_host = "nohost.invalid"\noperator_token = "{TOKEN}"\n',
        "control.tcp_host = 'nohost.invalid': cannot resolve",
    ),
    "too long socket path": (
        f'[control]\nsocket_path = "{LONG_DIR}/ctl.sock"\n',
        f"bytes, a Unix socket path holds at most {UNIX_PATH_MAX_BYTES}",
    ),
    "missing socket group": (
        '[control]\nsocket_group = "no-such-group-x"\n',
        "control.socket_group = 'no-such-group-x': no such group",
    ),
    "not a python-can interface": (
        '[link]\nkind = "can"\ncan_interface = "bogus"\n',
        "link.can_interface: interface 'bogus' is not a python-can interface",
    ),
    "not a serial url": ('[link]\nurl = "bogus://x"\n', "link.url: url 'bogus://x' is neither"),
    "rig file is a directory": ('[rig]\npath = "/tmp"\n', "/tmp: cannot read"),
    "socket path is a directory": (
        '[control]\nsocket_path = "/tmp"\n',
        "control.socket_path = '/tmp': exists and is not a socket",
    ),
}


@pytest.mark.parametrize("name", START_FAILURES)
def test_config_check_refuses_what_the_daemon_would_refuse(
    tmp_path: Path, name: str, capsys: pytest.CaptureFixture[str]
) -> None:
    text, expected = START_FAILURES[name]
    path = tmp_path / "orbitar.toml"
    path.write_text(text)
    assert cli_main(["config", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert expected in err
    assert "ok" not in err.split("\n")[-1]


def test_config_check_passes_a_good_file_and_shows_notes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "orbitar.toml"
    path.write_text(
        f'[link]\nurl = "/dev/ttyUSB97"\n[control]\nsocket_path = "{tmp_path}/ctl.sock"\n'
        f'[camera]\nsource = "{tmp_path}/missing.avi"\n'
    )
    assert cli_main(["config", "check", str(path)]) == 0
    captured = capsys.readouterr()
    assert captured.out == f"{path}: ok\n"
    assert "note: link.url = '/dev/ttyUSB97': no such device yet" in captured.err
    assert "camera.source = " in captured.err
    path.write_text('[link]\nkind = "xbee"\nurl = "socket://nohost.invalid:9750"\n')
    assert cli_main(["config", "check", str(path)]) == 0  # the link is retried until it resolves
    assert "link.url = 'socket://nohost.invalid:9750': cannot resolve" in capsys.readouterr().err


def test_an_output_receiver_that_does_not_resolve_is_a_note(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "orbitar.toml"
    path.write_text(
        f'[control]\nsocket_path = "{tmp_path}/ctl.sock"\n[outputs.freed]\nenabled = true\n'
        'destinations = ["127.0.0.1:40000", "nohost.invalid:1"]\n'
    )
    assert cli_main(["config", "check", str(path)]) == 0  # DNS down at boot must not stop it
    err = capsys.readouterr().err
    assert "note: outputs.freed.destinations[1] = 'nohost.invalid:1': cannot resolve" in err


def test_permissions_are_errors_only_for_the_service_itself(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    real_access = os.access
    # Root may write anywhere: answer for an unprivileged user, as os.access would for one.
    monkeypatch.setattr(os, "access", lambda p, mode: Path(p) != locked and real_access(p, mode))
    config = loads_config(f'[control]\nsocket_path = "{locked}/run/ctl.sock"\n')
    as_user, as_service = preflight(config), preflight(config, as_service=True)
    assert as_user.ok  # `config check` by another user than the service's: a note
    assert any(f"{locked} is not writable by uid" in n for n in as_user.notes)
    assert any(f"{locked} is not writable by uid" in e for e in as_service.errors)


async def test_the_daemon_refuses_at_start_naming_the_key(tmp_path: Path) -> None:
    config = tmp_path / "orbitar.toml"
    config.write_text(START_FAILURES["too long socket path"][0])
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.service", "daemon", "--config", str(config),
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    _, err = await asyncio.wait_for(proc.communicate(), 20.0)
    assert proc.returncode == 2
    assert "control.socket_path = '/tmp/ddd" in err.decode()
    assert "Traceback" not in err.decode()


# ---- SIGHUP with each bad file against a running daemon -------------------------------------

SHEAR = "[[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]"


def _rig(base: str, tmp: Path, name: str, rig_text: str) -> str:
    """The running config pointing at a new rig file holding `rig_text` (the rig's own file)."""
    rig = tmp / f"rig-{name}.toml"
    rig.write_text(rig_text + "\n")
    return base + f'[rig]\npath = "{rig}"\n'


def bad_reloads(base: str, tmp: Path) -> dict[str, tuple[str, str]]:
    """Each bad file of the issue as an edit of the running one, with the line it must log."""
    socket_line = f'socket_path = "{tmp}/ctl.sock"'
    deep = "[" * 3000 + "]" * 3000
    return {
        "scalar table": ("rig = 5\n" + base, "rig = 5: expected a table"),
        "deep nesting": (
            base + f"[registration]\nhorizon_ms = {deep}\n",
            "registration.horizon_ms: arrays or inline",
        ),
        "NUL": (base.replace(socket_line, socket_line[:-1] + '\\u0000"'), "U+0000"),
        "zero M_cr": (
            _rig(base, tmp, "z", "[head.m_cr]\nmatrix = [[0,0,0,1],[0,0,0,2],[0,0,0,3],[0,0,0,1]]"),
            "head.m_cr.matrix = ",
        ),
        "M_cr x10": (
            _rig(
                base, tmp, "x", "[head.m_cr]\nmatrix = [[10,0,0,0],[0,10,0,0],[0,0,10,0],[0,0,0,1]]"
            ),
            "singular values 10/10/10",
        ),
        "reflection": (
            _rig(
                base, tmp, "r", "[head.m_cr]\nmatrix = [[1,0,0,0],[0,1,0,0],[0,0,-1,0],[0,0,0,1]]"
            ),
            "a reflection",
        ),
        "sheared mount": (
            _rig(base, tmp, "s", f"[rangefinder.mount]\nmatrix = {SHEAR}"),
            "rangefinder.mount.matrix = ",
        ),
        "missing model": (
            _rig(base, tmp, "m", '[workpiece]\nmodel = "/nonexistent/p.obj"'),
            "workpiece.model = ",
        ),
        "long socket path": (
            base.replace(socket_line, f'socket_path = "{LONG_DIR}/c.sock"'),
            "control.socket_path = ",
        ),
        "tcp host": (
            base.replace(
                "[control]\n",
                f'[control]\ntcp_enabled = true\ntcp_host = "nohost.invalid"\n'
                f'operator_token = "{TOKEN}"\n',
            ),
            "control.tcp_host = 'nohost.invalid'",
        ),
    }


async def wait_logged(running: Running, needle: str, count: int, timeout_s: float = 10.0) -> str:
    """The daemon's log once `needle` appears in it `count` times."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while (text := await running.stderr_text()).count(needle) < count:
        assert running.proc.returncode is None, text
        assert loop.time() < deadline, text
        await asyncio.sleep(0.05)
    return text


async def next_freed_packet(running: Running) -> bytes:
    """A FreeD packet sent after this call (older ones are dropped)."""
    while not running.freed.packets.empty():
        running.freed.packets.get_nowait()
    return await asyncio.wait_for(running.freed.packets.get(), 10.0)


@pytest.fixture
async def daemon(tmp_path: Path) -> AsyncIterator[Running]:
    """A daemon on the fake controller, killed at the end if a test left it running."""
    running, transport = await start_daemon(tmp_path)
    try:
        yield running
    finally:
        if running.proc.returncode is None:
            running.proc.kill()
            await running.proc.wait()
        running.notes.sock.close()
        transport.close()


async def test_sighup_with_each_bad_file_keeps_the_daemon_and_its_settings(
    daemon: Running, tmp_path: Path
) -> None:
    await daemon.notes.wait_for("READY=1")
    base = daemon.config.read_text()
    async with await connect(tmp_path / "ctl.sock") as client:
        await client.request("home")
        await client.request("move", position_mm=500.0, speed_mm_s=200.0)
    await next_freed_packet(daemon)
    for n, (name, (text, expected)) in enumerate(bad_reloads(base, tmp_path).items(), 1):
        daemon.config.write_text(text)
        daemon.proc.send_signal(signal.SIGHUP)
        log = await wait_logged(daemon, "reload rejected", n)
        rejected = log.split("reload rejected")[n]
        assert expected in rejected.split("\n")[0], (name, rejected)
    assert "Traceback" not in log
    assert "reloaded applied" not in log  # nothing of a bad file was taken
    await next_freed_packet(daemon)  # the running outputs were not touched
    async with await connect(tmp_path / "ctl.sock") as client:
        status = await client.request("status")
        assert status["service"]["phase"] == "running"
    # Resolves, so the preflight passes, but cannot be opened (broadcast without permission):
    # the output is reported as not running, and the daemon goes on.
    daemon.config.write_text(base.replace('["127.0.0.1:', '["255.255.255.255:'))
    daemon.proc.send_signal(signal.SIGHUP)
    await wait_logged(daemon, "output not started output=freed", 1)
    await wait_logged(daemon, "reloaded applied=outputs", 1)
    async with await connect(tmp_path / "ctl.sock") as client:
        status = await client.request("status")
        assert "error" in status["service"]["freed"], status["service"]
    daemon.config.write_text(base.replace('level = "info"', 'level = "debug"'))
    daemon.proc.send_signal(signal.SIGHUP)
    await wait_logged(daemon, "reloaded applied=log,outputs", 1)
    await next_freed_packet(daemon)  # a good file brings the output back
    daemon.proc.send_signal(signal.SIGTERM)
    assert await asyncio.wait_for(daemon.proc.wait(), 5) == 0
