"""`orbitar install-service`: the service user, its directories, the config and the unit.

One step from an installed package to a unit systemd can start: the `orbitar` user and group
(with dialout and video for serial, slcan CAN and camera devices), /etc/orbitar with the
default config unless one exists, /var/lib/orbitar for recordings, and the unit with ExecStart
set to the entry point that runs this command. `--root DIR` writes the same files into a staging
root (users and ownership are shown, not changed), `--dry-run` only prints the plan.
"""

from __future__ import annotations

import argparse
import grp
import os
import pwd
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from host.service.unit import (
    DEFAULT_CONFIG,
    DEFAULT_STATE_DIR,
    UNIT_NAME,
    installed_executable,
    render_unit,
)

SERVICE_USER = SERVICE_GROUP = "orbitar"
DEVICE_GROUPS = ("dialout", "video")  # serial and slcan adapters; V4L2 cameras
UNIT_DIR = "/etc/systemd/system"
NOLOGIN = "/usr/sbin/nologin"
# DeviceAllow=char-ttyUSB (ttyACM, video4linux) finds its major in /proc/devices when the unit
# starts: a driver loaded later (the adapter plugged in after boot) would stay blocked until a
# restart. Loading the drivers at boot registers the majors before the service starts.
DEVICE_MODULES = ("usbserial", "cdc_acm", "videodev")
MODULES_LOAD = Path("/etc/modules-load.d/orbitar.conf")


@dataclass(frozen=True)
class Action:
    """One step of the installation: what it does, and how (None: only shown)."""

    what: str
    run: Callable[[], None] | None


def add_parser(subparsers: Any) -> None:
    """Register `orbitar install-service`."""
    parser = subparsers.add_parser(
        "install-service",
        help="set up the systemd service",
        description="Create the service user, its directories, the config and the systemd unit.",
    )
    parser.add_argument("--exec", dest="executable", help="orbitar executable for ExecStart")
    parser.add_argument("--config", default=DEFAULT_CONFIG, help="config file the unit uses")
    parser.add_argument("--root", default="/", help="staging root to write into (tests, images)")
    parser.add_argument("--dry-run", action="store_true", help="print the plan, change nothing")
    parser.add_argument("--allow-pty", action="store_true", help="allow ptys (simulator only)")
    parser.add_argument("--enable", action="store_true", help="then systemctl enable --now")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Plan, then carry out (or print) every step; 0 done, 1 failed, 2 the config is invalid."""
    root = Path(args.root).absolute()
    real = root == Path("/") and not args.dry_run
    if real and os.geteuid() != 0:
        print(
            "orbitar install-service: run it as root (or use --root DIR / --dry-run)",
            file=sys.stderr,
        )
        return 1
    if not os.path.isabs(args.config):
        print(f"orbitar install-service: --config {args.config}: must be absolute", file=sys.stderr)
        return 1
    try:
        executable = args.executable or installed_executable()
    except FileNotFoundError as exc:
        print(f"orbitar install-service: {exc}", file=sys.stderr)
        return 1
    actions = plan(root, executable, args.config, allow_pty=args.allow_pty)
    if real and args.enable:
        actions.append(_command(["systemctl", "enable", "--now", UNIT_NAME]))
    for action in actions:
        print(("would: " if args.dry_run else "") + action.what)
        if args.dry_run or action.run is None:
            continue
        try:
            action.run()
        except (OSError, subprocess.CalledProcessError) as exc:
            print(f"orbitar install-service: {action.what}: {exc}", file=sys.stderr)
            return 1
    return 0 if args.dry_run else _check_config(root, args.config)


def plan(root: Path, executable: str, config_path: str, *, allow_pty: bool = False) -> list[Action]:
    """Every step, in order; users, groups and ownership only act on the real root."""
    real = root == Path("/")
    actions = _account_actions(real)
    state = Path(DEFAULT_STATE_DIR)
    dirs = [
        (Path(config_path).parent, 0o755, "root", "root"),  # as ConfigurationDirectoryMode
        (state, 0o750, SERVICE_USER, SERVICE_GROUP),
        (state / "recordings", 0o750, SERVICE_USER, SERVICE_GROUP),
        (Path(UNIT_DIR), 0o755, "root", "root"),
    ]
    for path, mode, user, group in dirs:
        actions.append(_make_dir(root, path, mode, user, group, real))
    actions.append(_write_config(root, Path(config_path), real))
    actions.append(_write_modules_load(root, real))
    writable = _config_dirs(_staged(root, Path(config_path)))
    unit = render_unit(executable, config_path, writable, allow_pty=allow_pty)
    actions.append(
        _write_file(root, Path(UNIT_DIR) / UNIT_NAME, unit, 0o644, ("root", "root"), real)
    )
    if real and Path("/run/systemd/system").is_dir():
        actions.append(_command(["systemctl", "daemon-reload"]))
    return actions


def _account_actions(real: bool) -> list[Action]:
    """The device groups, the service group and the system user (only what is missing)."""
    actions = []
    for group in (*DEVICE_GROUPS, SERVICE_GROUP):
        if not _group_exists(group):
            actions.append(_command(["groupadd", "--system", group], real))
    if not _user_exists(SERVICE_USER):
        useradd = ["useradd", "--system", "--gid", SERVICE_GROUP, "--no-create-home"]
        useradd += ["--home-dir", DEFAULT_STATE_DIR, "--shell", NOLOGIN, SERVICE_USER]
        actions.append(_command(useradd, real))
    usermod = ["usermod", "--append", "--groups", ",".join(DEVICE_GROUPS), SERVICE_USER]
    actions.append(_command(usermod, real))
    return actions


def _command(argv: list[str], real: bool = True) -> Action:
    """Run a system command (shown only outside the real root)."""
    shown = " ".join(argv)
    if not real:
        return Action(f"{shown}  (staging root: not run)", None)

    def execute() -> None:
        subprocess.run(argv, check=True)

    return Action(shown, execute)


def _make_dir(root: Path, path: Path, mode: int, user: str, group: str, real: bool) -> Action:
    """A directory with its mode, and its owner on the real root."""
    target = _staged(root, path)

    def make() -> None:
        target.mkdir(parents=True, exist_ok=True)
        target.chmod(mode)
        if real:
            shutil.chown(target, user, group)

    return Action(f"mkdir {target} (mode {mode:04o}, owner {user}:{group})", make)


def _write_config(root: Path, path: Path, real: bool) -> Action:
    """The commented default config, unless a file is there already (it is never overwritten)."""
    target = _staged(root, path)
    if target.exists():
        return Action(f"keep {target} (exists)", None)
    from host.config import default_config_text

    return _write_file(root, path, default_config_text(), 0o640, ("root", SERVICE_GROUP), real)


def _write_file(
    root: Path, path: Path, text: str, mode: int, owner: tuple[str, str], real: bool
) -> Action:
    """A file with its mode, and its owner on the real root."""
    target = _staged(root, path)

    def write() -> None:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text, encoding="utf-8")
        target.chmod(mode)
        if real:
            shutil.chown(target, *owner)

    return Action(f"write {target} (mode {mode:04o}, owner {owner[0]}:{owner[1]})", write)


def _config_dirs(path: Path) -> tuple[str, ...]:
    """Where an existing config makes the daemon write: recordings, the control socket."""
    from host.config import load_config
    from host.config_fields import ConfigError

    try:
        config = load_config(path)
    except ConfigError:
        return ()  # a missing file becomes the default; a bad one fails the check at the end
    return (config.recording.dir, str(Path(config.control.socket_path).parent))


def kernel_modules(names: tuple[str, ...], moddir: Path | None = None) -> list[str]:
    """Those of `names` this kernel has, as a module or built in (modules.dep, modules.builtin)."""
    moddir = moddir or Path("/lib/modules") / os.uname().release
    known = set()
    for index in ("modules.dep", "modules.builtin"):
        try:
            lines = (moddir / index).read_text(encoding="utf-8").splitlines()
        except OSError:
            continue
        for line in lines:
            known.add(Path(line.split(":", 1)[0]).name.split(".ko")[0].replace("-", "_"))
    return [n for n in names if n in known or Path("/sys/module", n).is_dir()]


def _write_modules_load(root: Path, real: bool) -> Action:
    """Load the serial and camera drivers at boot, so their device groups exist at start."""
    found = kernel_modules(DEVICE_MODULES)
    if not found:
        names = ", ".join(DEVICE_MODULES)
        return Action(f"no {MODULES_LOAD}: this kernel lists none of {names}", None)
    text = "# orbitar.service: the majors DeviceAllow=char-ttyUSB/ttyACM/video4linux need\n"
    return _write_file(
        root, MODULES_LOAD, text + "\n".join(found) + "\n", 0o644, ("root", "root"), real
    )


def _check_config(root: Path, config_path: str) -> int:
    """`config check` on the installed file, so the first start does not fail on it."""
    from host.service.preflight import check_file

    path = _staged(root, Path(config_path))
    _, report = check_file(path)
    for line in report.notes:
        print(f"{path}: note: {line}")
    if not report.ok:
        print(f"{path}: invalid configuration:\n  " + "\n  ".join(report.errors), file=sys.stderr)
        return 2
    print(f"{path}: ok. Start with: systemctl enable --now {UNIT_NAME}")
    return 0


def _staged(root: Path, path: Path) -> Path:
    """`path` inside the staging root."""
    return root / path.relative_to("/") if path.is_absolute() else root / path


def _group_exists(name: str) -> bool:
    try:
        grp.getgrnam(name)
    except KeyError:
        return False
    return True


def _user_exists(name: str) -> bool:
    try:
        pwd.getpwnam(name)
    except KeyError:
        return False
    return True
