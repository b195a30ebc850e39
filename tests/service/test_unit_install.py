"""`orbitar install-service` into a staging root: the files, `systemd-analyze verify` and the
sandbox's exposure score, with the camera, serial and CAN devices still reachable."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from host.cli import main as cli_main
from host.config import Config, load_config
from host.service import install as install_module
from host.service.unit import installed_executable, render_unit, under_home

ANALYZE = shutil.which("systemd-analyze")
needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze is not installed")
ORBITAR = Path(sys.executable).with_name("orbitar")  # the venv's entry point
MAX_EXPOSURE = 3.5


def install(root: Path, *extra: str) -> int:
    return cli_main(["install-service", "--root", str(root), "--exec", str(ORBITAR), *extra])


def analyze(*args: str) -> subprocess.CompletedProcess[str]:
    assert ANALYZE is not None
    return subprocess.run([ANALYZE, *args], capture_output=True, text=True, timeout=60)


def test_install_stages_user_dirs_config_and_unit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert install(tmp_path) == 0
    out = capsys.readouterr().out
    assert "usermod --append --groups dialout,video orbitar" in out
    unit = (tmp_path / "etc/systemd/system/orbitar.service").read_text()
    assert f"ExecStart={ORBITAR} daemon --config /etc/orbitar/orbitar.toml" in unit
    assert load_config(tmp_path / "etc/orbitar/orbitar.toml") == Config()
    assert (tmp_path / "var/lib/orbitar/recordings").is_dir()
    assert (tmp_path / "etc/orbitar").stat().st_mode & 0o777 == 0o755
    assert (tmp_path / "etc/orbitar/orbitar.toml").stat().st_mode & 0o777 == 0o640
    assert "orbitar.toml: ok" in out


def test_an_existing_config_is_kept_and_dry_run_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "etc/orbitar/orbitar.toml"
    config.parent.mkdir(parents=True)
    config.write_text('[log]\nlevel = "debug"\n')
    assert install(tmp_path) == 0
    assert config.read_text() == '[log]\nlevel = "debug"\n'
    assert "keep " in capsys.readouterr().out
    assert install(tmp_path, "--config", "orbitar.toml") == 1  # ExecStart needs an absolute path
    dry = tmp_path / "dry"
    assert install(dry, "--dry-run") == 0
    assert not dry.exists()
    assert "would: write " in capsys.readouterr().out


def test_an_invalid_existing_config_fails_the_install_by_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "etc/orbitar/orbitar.toml"
    config.parent.mkdir(parents=True)
    config.write_text("rig = 5\n")
    assert install(tmp_path) == 2
    assert "rig = 5: expected a table" in capsys.readouterr().err


def test_protect_home_follows_where_the_program_lives(tmp_path: Path) -> None:
    system_script = tmp_path / "orbitar"
    system_script.write_text("#!/usr/bin/python3\n")
    home_venv = tmp_path / "orbitar-home"
    home_venv.write_text("#!/home/op/venv/bin/python\n")
    assert "\nProtectHome=yes\n" in render_unit(str(system_script))
    assert "\nProtectHome=read-only\n" in render_unit(str(home_venv))  # the venv stays readable
    assert "\nProtectHome=read-only\n" in render_unit("/home/op/.local/bin/orbitar")
    assert under_home("/root/venv/bin/orbitar")


def test_ptys_only_on_request(tmp_path: Path) -> None:
    assert "char-pts" not in render_unit(str(ORBITAR))
    assert "\nDeviceAllow=char-pts rw\n" in render_unit(str(ORBITAR), allow_pty=True)


@needs_analyze
@pytest.mark.parametrize("recording_dir", ["/var/lib/orbitar/recordings", "/srv/orbitar rec"])
def test_systemd_analyze_verify_accepts_the_installed_unit(
    tmp_path: Path, recording_dir: str
) -> None:
    config = tmp_path / "etc/orbitar/orbitar.toml"
    config.parent.mkdir(parents=True)
    config.write_text(f'[recording]\ndir = "{recording_dir}"\n')
    assert install(tmp_path) == 0
    unit = tmp_path / "etc/systemd/system/orbitar.service"
    result = analyze("verify", str(unit))
    assert result.returncode == 0, result.stderr
    assert "orbitar.service" not in result.stderr, result.stderr  # not even a warning


@needs_analyze
def test_the_template_as_shipped_is_refused_by_verify(tmp_path: Path) -> None:
    unit = tmp_path / "orbitar.service"
    unit.write_text(render_unit("/usr/bin/orbitar-not-installed"))
    assert analyze("verify", str(unit)).returncode != 0  # so the check above can fail


@needs_analyze
@pytest.mark.parametrize("program", ["system", "home"])
def test_security_exposure_is_at_most_3_5_with_devices_reachable(
    tmp_path: Path, program: str
) -> None:
    script = tmp_path / "orbitar"
    script.write_text(
        "#!/usr/bin/python3\n" if program == "system" else "#!/home/op/v/bin/python\n"
    )
    unit = tmp_path / "orbitar.service"
    unit.write_text(render_unit(str(script)))
    result = analyze("security", "--offline=true", str(unit))
    if "--offline" in result.stderr and result.returncode != 0:
        pytest.skip(f"systemd-analyze security --offline unsupported: {result.stderr.strip()}")
    found = re.search(r"Overall exposure level for orbitar\.service: (\d+\.\d+)", result.stdout)
    assert found, result.stdout + result.stderr
    assert float(found.group(1)) <= MAX_EXPOSURE, result.stdout
    devices = re.search(r"device ACL with some special devices: (.*?)\s{2,}", result.stdout)
    assert devices, result.stdout
    acl = devices.group(1).split()
    for device in ("ttyS", "ttyUSB", "ttyACM", "video4linux"):
        assert f"char-{device}:rw" in acl  # serial, slcan CAN, camera
    assert not any(d.startswith("char-pts") for d in acl)
    assert "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6 AF_CAN AF_NETLINK" in unit.read_text()


def test_device_drivers_are_loaded_at_boot_where_the_kernel_has_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    moddir = tmp_path / "modules"
    moddir.mkdir()
    (moddir / "modules.dep").write_text(
        "kernel/drivers/usb/serial/usbserial.ko.xz:\n"
        "kernel/drivers/usb/class/cdc-acm.ko.xz: kernel/drivers/usb/serial/usbserial.ko.xz\n"
    )
    (moddir / "modules.builtin").write_text("kernel/drivers/media/v4l2-core/videodev.ko\n")
    assert install_module.kernel_modules(install_module.DEVICE_MODULES, moddir) == [
        "usbserial",
        "cdc_acm",
        "videodev",
    ]
    assert install_module.kernel_modules(("no_such_driver",), moddir) == []
    monkeypatch.setattr(install_module, "kernel_modules", lambda names: ["usbserial", "cdc_acm"])
    root = tmp_path / "root"
    assert install(root) == 0
    conf = (root / "etc/modules-load.d/orbitar.conf").read_text().splitlines()
    assert conf[1:] == ["usbserial", "cdc_acm"]


@needs_analyze
def test_a_program_path_with_blanks_and_percent_is_one_execstart_word(tmp_path: Path) -> None:
    program = tmp_path / "my venv 100%" / "orbitar"
    program.parent.mkdir()
    program.write_text("#!/usr/bin/python3\n")
    program.chmod(0o755)
    unit = tmp_path / "orbitar.service"
    unit.write_text(render_unit(str(program), "/etc/orbitar/orbitar.toml"))
    assert f'ExecStart="{tmp_path}/my venv 100%%/orbitar" daemon --config' in unit.read_text()
    result = analyze("verify", str(unit))
    assert result.returncode == 0, result.stderr  # verify finds the program: the word is whole


def test_directories_an_existing_config_writes_are_made_writable(tmp_path: Path) -> None:
    config = tmp_path / "etc/orbitar/orbitar.toml"
    config.parent.mkdir(parents=True)
    config.write_text(
        '[recording]\ndir = "/srv/orbitar rec"\n[control]\nsocket_path = "/run/orbitar/c.sock"\n'
    )
    assert install(tmp_path) == 0
    unit = (tmp_path / "etc/systemd/system/orbitar.service").read_text()
    assert 'ReadWritePaths=-/var/lib/orbitar "-/srv/orbitar rec"\n' in unit  # /run/orbitar: own


def test_execstart_is_the_entry_point_that_is_installed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert cli_main(["install-service", "--root", str(tmp_path)]) == 0
    unit = (tmp_path / "etc/systemd/system/orbitar.service").read_text()
    assert f"ExecStart={ORBITAR} daemon" in unit  # the venv's script beside this python
    monkeypatch.setattr(sys, "executable", str(tmp_path / "python"))
    monkeypatch.setattr(sys, "argv", [str(tmp_path / "cli.py")])
    monkeypatch.setenv("PATH", str(tmp_path / "nothing"))
    with pytest.raises(FileNotFoundError, match="pass --exec"):
        installed_executable()
