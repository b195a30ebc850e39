"""The CLI commands against a live control socket (subprocesses, as a user runs them)."""

from __future__ import annotations

import asyncio
import io
import json
import math
import os
import sys
import time
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
    code, out, _ = await cli("move", "1500", "--speed", "80", "--no-wait", "--socket", sock)
    assert (code, out.strip()) == (0, "ok")
    assert (await cli("head", "90", "-30", "--socket", sock))[0] == 0
    assert (await cli("estop", "--socket", sock))[0] == 0
    assert fake.calls[-3][1] == (1500.0, 80.0)
    assert fake.head_rad == pytest.approx((math.pi / 2, -math.pi / 6))
    assert fake.state.name == "ESTOP"


async def test_home_and_move_wait_until_the_trolley_is_there(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    _, fake, sock = served
    code, out, _ = await cli("home", "--socket", sock)
    assert code == 0
    assert out.startswith("home done: READY"), out
    # the fake travels at 400 mm/s: the command returns once it is READY at 600 mm, not before
    code, out, _ = await cli("move", "600", "--speed", "400", "--socket", sock)
    assert code == 0
    assert out.startswith("move done: READY"), out
    assert "position 600.0 mm" in out, out
    assert fake.position_mm == pytest.approx(600.0)
    code, out, _ = await cli("move", "100", "--speed", "400", "--json", "--socket", sock)
    assert code == 0
    done = json.loads(out)
    assert (done["state"], done["position_mm"]) == ("READY", pytest.approx(100.0))


async def test_a_move_that_latches_exits_1_naming_the_state(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    _, fake, sock = served
    assert (await cli("home", "--socket", sock))[0] == 0
    waiting = asyncio.create_task(cli("move", "5000", "--speed", "100", "--socket", sock))
    await asyncio.sleep(1.5)  # the command is following the move by now
    await fake.estop()
    code, _, err = await asyncio.wait_for(waiting, 30)
    assert code == 1
    assert "move: the controller latched: ESTOP" in err, err


async def test_status_reads_in_degrees_millimetres_and_ages(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    _, fake, sock = served
    await fake.set_head(math.radians(12.5), math.radians(-20.0))
    code, out, _ = await cli("status", "--socket", sock)
    assert code == 0
    lines = {line.split()[0]: line for line in out.splitlines()}
    assert lines["controller"].split()[1] == "IDLE"
    assert "no faults" in lines["controller"]
    assert "pan 12.50°" in lines["head"]
    assert "tilt -20.00°" in lines["head"]
    assert "x 10.0  y 20.0  z 4000.0 mm" in lines["camera"]
    assert "old" in lines["camera"]  # every pose says how old it is
    assert "[[" not in out  # no raw matrices
    code, out, _ = await cli("status", "--json", "--socket", sock)
    assert json.loads(out)["link_up"] is True


async def test_head_errors_answer_in_degrees(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    code, _, err = await cli("head", "0", "100", "--socket", served[2])
    assert code == 1
    assert "tilt 100.00° is outside the head's limits [-90.00°, 90.00°]" in err


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


async def test_watch_redraws_at_a_readable_rate(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    server, _, sock = served
    proc = asyncio.create_task(cli("watch", "--count", "3", "--socket", sock))
    t0 = time.monotonic()
    sent = 0
    while not proc.done():  # 50 events a second; the screen redraws 4 times a second
        server.publish("pose", POSE.to_dict())
        server.publish("state", {"state": "MOVING", "position_mm": 12.5, "fault_names": ["ESTOP"]})
        sent += 1
        await asyncio.sleep(0.02)
    code, out, _ = await proc
    assert code == 0
    assert out.count("controller ") == 3
    assert "MOVING · FAULTS: ESTOP · position 12.5 mm" in out
    assert "pan 0.00°" in out
    assert sent > 3 * 5  # many events were folded into each redraw
    assert time.monotonic() - t0 > 0.4


async def test_watch_json_prints_one_event_per_line(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    server, _, sock = served
    proc = asyncio.create_task(cli("watch", "--json", "--count", "4", "--socket", sock))
    while not proc.done():
        server.publish("state", {"state": "READY", "position_mm": 1.0})
        await asyncio.sleep(0.05)
    code, out, _ = await proc
    assert code == 0
    events = [json.loads(line) for line in out.splitlines()]
    assert len(events) == 4
    assert events[0] == {"topic": "state", "data": {"state": "READY", "position_mm": 1.0}}


async def test_watch_says_when_updates_stop(
    served: tuple[ControlServer, MemoryController, str],
) -> None:
    code, out, _ = await cli("watch", "--count", "12", "--rate", "5", "--socket", served[2])
    assert code == 0
    assert "NO UPDATES for" in out


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
