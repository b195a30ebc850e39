"""The CLI commands against a live control socket (subprocesses, as a user runs them)."""

from __future__ import annotations

import asyncio
import io
import math
import os
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from host.config import Config, ControlConfig, loads_config
from host.control.api import PoseSample
from host.control.cli_commands import emit
from host.control.ops import OpContext
from host.control.server import ControlServer
from tests.fakes import MemoryController

POSE = PoseSample(1, ((1, 0, 0, 10.0), (0, 0, 1, 20.0), (0, -1, 0, 4000.0), (0, 0, 0, 1)), "READY")


async def cli(*argv: str) -> tuple[int, str, str]:
    """Run `python -m host.control ARGV` and collect exit code, stdout, stderr."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.control", *argv,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, out.decode(), err.decode()


@pytest.fixture
async def served(tmp_path: Path) -> AsyncIterator[tuple[ControlServer, MemoryController, str]]:
    fake = MemoryController()
    await fake.connect()
    config = ControlConfig(socket_path=str(tmp_path / "c.sock"))
    server = ControlServer(OpContext(fake, latest_pose=lambda: POSE), config)
    await server.start()
    yield server, fake, config.socket_path
    await server.close()


async def test_motion_commands(served: tuple[ControlServer, MemoryController, str]) -> None:
    _, fake, sock = served
    assert (await cli("home", "--socket", sock))[0] == 0
    code, out, _ = await cli("move", "1500", "--speed", "80", "--socket", sock)
    assert (code, out.strip()) == (0, "ok")
    assert (await cli("head", "90", "-30", "--socket", sock))[0] == 0
    assert (await cli("estop", "--socket", sock))[0] == 0
    assert fake.calls[-3][1] == (1500.0, 80.0)
    assert fake.head_rad == pytest.approx((math.pi / 2, -math.pi / 6))
    assert fake.state.name == "ESTOP"


async def test_status_prints_fields(served: tuple[ControlServer, MemoryController, str]) -> None:
    code, out, _ = await cli("status", "--socket", served[2])
    assert code == 0
    assert "link_up: True" in out
    assert "state: IDLE" in out


async def test_refused_request_exits_1_with_reason(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    code, _, err = await cli("move", "100", "--socket", served[2])  # not homed
    assert code == 1
    assert "move refused: failed" in err
    code, _, err = await cli("head", "0", "100", "--socket", served[2])
    assert code == 1
    assert "out_of_range" in err


async def test_no_daemon_exits_1(tmp_path: Path) -> None:
    code, _, err = await cli("status", "--socket", str(tmp_path / "none.sock"))
    assert code == 1
    assert "daemon not running" in err


async def test_watch_counts_updates(served: tuple[ControlServer, MemoryController, str]) -> None:
    server, _, sock = served
    proc = asyncio.create_task(cli("watch", "--count", "3", "--socket", sock))
    while not proc.done():
        server.publish("pose", POSE.to_dict())
        server.publish("state", {"state": "MOVING", "position_mm": 12.5})
        await asyncio.sleep(0.05)
    code, out, _ = await proc
    assert code == 0
    assert "camera_mm: 10.0 20.0 4000.0" in out or "state: MOVING" in out
    assert out.count("state:") == 3


async def test_config_check_and_default(tmp_path: Path) -> None:
    code, text, _ = await cli("config", "default")
    assert code == 0
    assert loads_config(text) == Config()
    bad = tmp_path / "bad.toml"
    bad.write_text('[link]\nkind = "x"\nbaud = 0\n')
    code, _, err = await cli("config", "check", str(bad))
    assert code == 2
    assert "link.kind" in err
    assert "link.baud" in err
    good = tmp_path / "good.toml"
    good.write_text(text)
    assert (await cli("config", "check", str(good)))[0] == 0


async def test_systemd_unit_prints_the_unit() -> None:
    code, out, _ = await cli("systemd-unit", "--exec", "/opt/o/bin/orbitar")
    assert code == 0
    assert "ExecStart=/opt/o/bin/orbitar daemon --config /etc/orbitar/orbitar.toml" in out


async def closed_pipe_cli(*argv: str) -> tuple[int, str]:
    """Run `python -m host.cli ARGV` (the `orbitar` entry point) into a pipe nobody reads."""
    read_fd, write_fd = os.pipe()
    os.close(read_fd)  # the reader is gone before the first byte: every write hits EPIPE
    try:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "host.cli", *argv,
            stdout=write_fd, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
    finally:
        os.close(write_fd)
    _, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, err.decode()


async def test_status_into_a_closed_pipe_exits_quietly(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    for argv in (("status",), ("status", "--json"), ("home",)):
        code, err = await closed_pipe_cli(*argv, "--socket", served[2])
        assert (code, err) == (0, ""), argv
    assert (await closed_pipe_cli("config", "default")) == (0, "")


def test_emit_reports_a_gone_reader_and_silences_the_stream() -> None:
    read_fd, write_fd = os.pipe()
    with open(write_fd, "w", encoding="utf-8") as stream:
        assert emit("first\n", stream)
        assert os.read(read_fd, 100) == b"first\n"
        os.close(read_fd)
        assert not emit("state: IDLE\n" * 1000, stream)
        stream.write("after\n")  # lands in /dev/null now, as the exit-time flush will
        stream.flush()
        assert os.path.samestat(os.fstat(stream.fileno()), os.stat(os.devnull))
    assert emit("kept\n", buffer := io.StringIO())  # streams without a descriptor still work
    assert buffer.getvalue() == "kept\n"
