"""The daemon reads its rig from the rig file and picks a changed one up on SIGHUP."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from host.config import load_config
from host.service.daemon import Daemon
from host.service.wiring import PosePublisher, controller_factory, frame_loop_factory

RIG = """
[track.home]
value_mm = {home}
[head.m_cr]
matrix = [[1, 0, 0, {x}], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
"""


def _daemon(tmp_path: Path) -> tuple[Daemon, Path]:
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG.format(home=100.0, x=50.0))
    config = tmp_path / "orbitar.toml"
    config.write_text(
        f'[rig]\npath = "{rig}"\n[camera]\nsource = "none"\n'
        f'[control]\nsocket_path = "{tmp_path}/ctl.sock"\n'
    )
    daemon = Daemon(load_config(config), controller_factory, frame_loop_factory, config_path=config)
    return daemon, rig


def _rewrite(rig: Path, text: str) -> None:
    """Write the file and move its mtime on, as a later commissioning run would."""
    st = rig.stat()
    rig.write_text(text)
    os.utime(rig, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))


async def test_sighup_applies_a_changed_rig_file(tmp_path: Path) -> None:
    daemon, rig = _daemon(tmp_path)
    loop = daemon.frame_loop
    assert isinstance(loop, PosePublisher)
    assert loop.feed is not None
    assert loop.feed.home_s_mm == 100.0
    assert loop.poses.rig.T_r_c[0, 3] == 50.0
    _rewrite(rig, RIG.format(home=250.0, x=51.5))
    assert await daemon.reload() == ["rig"]
    assert loop.feed.home_s_mm == 250.0
    assert loop.poses.rig.T_r_c[0, 3] == 51.5
    assert daemon.calibration()["m_cr"][0][3] == 51.5
    assert await daemon.reload() == []  # unchanged: nothing to apply


async def test_a_bad_rig_file_on_sighup_keeps_the_running_rig(tmp_path: Path) -> None:
    daemon, rig = _daemon(tmp_path)
    loop = daemon.frame_loop
    assert isinstance(loop, PosePublisher)
    before = np.array(loop.poses.rig.T_r_c)
    _rewrite(rig, "[camera]\nfps = 0\n")
    assert await daemon.reload() == []
    assert loop.feed is not None
    assert loop.feed.home_s_mm == 100.0
    np.testing.assert_array_equal(loop.poses.rig.T_r_c, before)
