"""The shipped systemd unit: its settings, and `systemd-analyze verify` where the tool exists."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from host.service.unit import render_unit, unit_template

REQUIRED = [
    "Type=notify",
    "NotifyAccess=main",
    "WatchdogSec=10",
    "Restart=on-failure",
    "SupplementaryGroups=dialout video",
    "UMask=0027",
    "CapabilityBoundingSet=",
    "SystemCallFilter=@system-service",
    "RuntimeDirectory=orbitar",
    "ProtectSystem=strict",
    "NoNewPrivileges=yes",
    "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_CAN AF_NETLINK",
    "DeviceAllow=char-ttyUSB rw",
    "DeviceAllow=char-ttyACM rw",
    "DeviceAllow=char-ttyS rw",
    "DeviceAllow=char-video4linux rw",
]


def test_unit_has_the_required_settings() -> None:
    lines = unit_template().splitlines()
    for setting in REQUIRED:
        assert setting in lines, setting
    assert "PrivateDevices=yes" not in lines  # it would hide the serial adapters
    assert not any("char-pts" in line for line in lines)  # a pty is the simulator's, not a rig's


def test_render_fills_exec_and_recording_dir() -> None:
    text = render_unit(
        "/opt/orbitar/bin/orbitar", "/etc/o.toml", ("/srv/recordings", "/run/orbitar")
    )
    assert "ExecStart=/opt/orbitar/bin/orbitar daemon --config /etc/o.toml" in text
    assert "ReadWritePaths=-/var/lib/orbitar -/srv/recordings" in text


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze missing")
def test_systemd_analyze_verify_accepts_it(tmp_path: Path) -> None:
    orbitar = Path(sys.executable).with_name("orbitar")
    assert orbitar.exists()
    unit = tmp_path / "orbitar.service"
    unit.write_text(render_unit(str(orbitar), str(tmp_path / "orbitar.toml")))
    result = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert "orbitar.service" not in result.stderr, result.stderr  # no warning about our unit


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze missing")
def test_systemd_analyze_verify_rejects_a_broken_unit(tmp_path: Path) -> None:
    unit = tmp_path / "orbitar.service"
    unit.write_text(render_unit(str(tmp_path / "no-such-binary")))
    result = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    assert result.returncode != 0  # the check above can fail
