"""`orbitar sim` as users run it: a subprocess, its printed connection, a handshake, SIGTERM."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import sys
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from hil_sim.cli import SimOptions, SimOptionsError, build_options, load_table
from host.link import Controller
from host.transport import Transport, create_transport

READY_MARK = "press Ctrl-C"
START_TIMEOUT_S = 20.0


@dataclass
class Sim:
    """A running `orbitar sim` and what it printed up to its ready line."""

    proc: asyncio.subprocess.Process
    lines: list[str]

    def value(self, key: str) -> str:
        """A `key = value` line of the printed [link] table, unquoted."""
        for line in self.lines:
            match = re.fullmatch(rf"\s*{key} = (.*)", line)
            if match:
                return match.group(1).strip('"')
        raise KeyError(key)


async def start_sim(*args: str) -> Sim:
    """`python -m host.cli sim ARGS` (the registered subcommand), up to its ready line."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.cli", "sim", *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert proc.stdout is not None
    lines: list[str] = []
    while not lines or READY_MARK not in lines[-1]:
        raw = await asyncio.wait_for(proc.stdout.readline(), START_TIMEOUT_S)
        if not raw:
            err = await proc.stderr.read() if proc.stderr else b""
            raise AssertionError(f"sim ended before it was ready: {lines} {err.decode()}")
        lines.append(raw.decode().rstrip("\n"))
    return Sim(proc, lines)


async def terminate(sim: Sim, timeout_s: float = 5.0) -> int:
    """SIGTERM and the exit code (killed if it does not stop in time)."""
    if sim.proc.returncode is None:
        sim.proc.send_signal(signal.SIGTERM)
    try:
        await asyncio.wait_for(sim.proc.communicate(), timeout_s)
    except TimeoutError:
        sim.proc.kill()
        await sim.proc.wait()
    assert sim.proc.returncode is not None
    return sim.proc.returncode


@pytest.fixture
async def sims() -> AsyncIterator[list[Sim]]:
    """Every sim a test starts is gone when it ends."""
    started: list[Sim] = []
    yield started
    for sim in started:
        await terminate(sim)


async def handshake(transport: Transport) -> None:
    """Connect the host's controller, check IDENTIFY, close."""
    ctrl = Controller(transport)
    try:
        ident = await asyncio.wait_for(ctrl.connect(), 15.0)
        assert ident.encoder_counts_per_rev == 4000  # 1000 lines × 4
        assert ident.sprocket_teeth == 20
        assert ctrl.session.stats.handshakes == 1
    finally:
        await ctrl.close()


async def test_pty_sim_serves_the_host_and_cleans_up(tmp_path: Path, sims: list[Sim]) -> None:
    link = tmp_path / "sim"
    sim = await start_sim("--link", "pty", "--link-path", str(link), "--seed", "3")
    sims.append(sim)
    assert link.is_symlink()
    assert os.readlink(link).startswith("/dev/pts/")
    assert sim.value("kind") == "serial"
    assert sim.value("url") == str(link)
    assert int(sim.value("baud")) == 115200
    assert any("seed 3" in line for line in sim.lines)
    await handshake(create_transport("serial", url=str(link), baudrate=115200))
    assert await terminate(sim) == 0
    assert not link.exists()
    assert not link.is_symlink()


async def test_tcp_sim_prints_a_socket_url(sims: list[Sim]) -> None:
    sim = await start_sim("--link", "tcp")
    sims.append(sim)
    url = sim.value("url")
    assert re.fullmatch(r"socket://127\.0\.0\.1:\d+", url)
    await handshake(create_transport("serial", url=url, baudrate=115200))
    assert await terminate(sim) == 0


async def test_xbee_sim_prints_address_and_mode(tmp_path: Path, sims: list[Sim]) -> None:
    link = tmp_path / "xbee"
    sim = await start_sim("--link", "xbee", "--link-path", str(link), "--api-mode", "1")
    sims.append(sim)
    assert sim.value("kind") == "xbee"
    assert int(sim.value("xbee_api_mode")) == 1
    transport = create_transport(
        "xbee", url=str(link), api_mode=1, dest_addr64=sim.value("xbee_address")
    )
    await handshake(transport)
    assert await terminate(sim) == 0
    assert not link.is_symlink()


async def test_can_sim_is_an_slcan_adapter_across_processes(
    tmp_path: Path, sims: list[Sim]
) -> None:
    link = tmp_path / "slcan"
    sim = await start_sim("--link", "can", "--link-path", str(link), "--node-id", "5")
    sims.append(sim)
    assert sim.value("can_interface") == "slcan"
    assert sim.value("can_channel") == str(link)
    transport = create_transport(
        "can", interface="slcan", channel=str(link), node_id=5, bitrate=500_000
    )
    await handshake(transport)
    assert await terminate(sim) == 0


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--drop-rate", "1.5"], "drop_rate = 1.5: must be within [0, 1]"),
        (["--link", "serial"], "invalid choice: 'serial'"),
        (["--marks", "100,abc"], "expected MM,MM"),
        (["--speed", "0"], "speed = 0.0: must be within"),
    ],
)
async def test_bad_options_exit_2_with_a_clear_message(args: list[str], needle: str) -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "hil_sim", *args,
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, err = await asyncio.wait_for(proc.communicate(), 20.0)
    assert proc.returncode == 2, (out, err)
    assert needle in err.decode()
    assert READY_MARK not in out.decode()


def test_config_file_names_bad_keys_and_values(tmp_path: Path) -> None:
    path = tmp_path / "sim.toml"
    path.write_text('link = "tcp"\nspeeed = 2.0\nbaud = "fast"\nmarks = [1000, "x"]\n')
    with pytest.raises(SimOptionsError) as info:
        build_options(load_table(str(path)), {})
    problems = "\n".join(info.value.problems)
    assert "speeed: unknown key" in problems
    assert "baud = 'fast': expected an integer" in problems
    assert "marks = [1000, 'x']: not positions in mm: ['x']" in problems
    assert len(info.value.problems) == 3


def test_config_file_then_command_line_precedence(tmp_path: Path) -> None:
    path = tmp_path / "sim.toml"
    path.write_text('[sim]\nlink = "xbee"\nseed = 9\nmarks = [1000, 3000.5]\nlatency_ms = 4\n')
    options = build_options(load_table(str(path)), {"seed": 11, "link": None})
    assert options == SimOptions(link="xbee", seed=11, marks=(1000.0, 3000.5), latency_ms=4.0)
    assert build_options({}, {}) == SimOptions()


def test_unreadable_config_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(SimOptionsError, match="cannot read"):
        load_table(str(tmp_path / "missing.toml"))
    (tmp_path / "bad.toml").write_text("link = \n")
    with pytest.raises(SimOptionsError, match="TOML syntax"):
        load_table(str(tmp_path / "bad.toml"))


OPEN_RIG = """
[[track.segments]]
kind = "straight"
length_mm = 2500.0
[[track.segments]]
kind = "arc"
radius_mm = 600.0
angle_deg = -120.0
[track.home]
value_mm = 120.0
"""


async def test_bad_rig_file_exits_2_naming_the_key(tmp_path: Path) -> None:
    rig = tmp_path / "rig.toml"
    rig.write_text("[camera]\nwidth = -5\n")
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "hil_sim", "--rig", str(rig),
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, err = await asyncio.wait_for(proc.communicate(), 20.0)
    assert proc.returncode == 2, (out, err)
    assert "camera.width = -5: out of range" in err.decode()


def test_rig_file_is_the_simulated_track_and_tolerances_are_seeded(tmp_path: Path) -> None:
    from hil_sim.cli import make_scenario

    rig = tmp_path / "rig.toml"
    rig.write_text(OPEN_RIG)
    exact = make_scenario(SimOptions(rig=str(rig), seed=3))
    assert not exact.track.closed
    assert exact.track.home_s_mm == 120.0
    assert exact.track.length_mm == pytest.approx(2500.0 + 600.0 * 2 * 3.141592653589793 / 3)
    a = make_scenario(SimOptions(rig=str(rig), seed=3, tolerances=True))
    b = make_scenario(SimOptions(rig=str(rig), seed=3, tolerances=True))
    c = make_scenario(SimOptions(rig=str(rig), seed=4, tolerances=True))
    assert a.track.length_mm == b.track.length_mm != c.track.length_mm
    assert a.track.length_mm != exact.track.length_mm
