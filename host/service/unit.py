"""The systemd unit shipped with the package, rendered for the installed executable and paths."""

from __future__ import annotations

import os
import shutil
import sys
from importlib import resources
from pathlib import Path

UNIT_NAME = "orbitar.service"
TEMPLATE_EXEC = "/usr/bin/orbitar"  # the placeholder in host/data; no package installs it there
DEFAULT_CONFIG = "/etc/orbitar/orbitar.toml"
DEFAULT_STATE_DIR = "/var/lib/orbitar"
SANDBOX_WRITABLE = (DEFAULT_STATE_DIR, "/run/orbitar")  # StateDirectory=, RuntimeDirectory=
ENTRY_POINT = "orbitar"
# Where ProtectHome=yes would hide the program (a venv in a home directory).
HOME_PREFIXES = ("/home/", "/root/", "/run/user/")
PTY_DEVICES = "DeviceAllow=char-pts rw"  # only for the simulator's pty link, never in production


def unit_template() -> str:
    """The unit file as shipped in host/data."""
    return resources.files("host").joinpath("data", UNIT_NAME).read_text(encoding="utf-8")


def installed_executable() -> str:
    """Absolute path of the `orbitar` entry point that runs now (argv[0], beside python, PATH)."""
    candidates = [sys.argv[0] if Path(sys.argv[0]).name == ENTRY_POINT else ""]
    candidates.append(str(Path(sys.executable).with_name(ENTRY_POINT)))
    candidates.append(shutil.which(ENTRY_POINT) or "")
    for candidate in candidates:
        if candidate and os.access(candidate, os.X_OK) and Path(candidate).is_file():
            return str(Path(candidate).absolute())
    raise FileNotFoundError(
        f"no {ENTRY_POINT!r} executable found (argv[0], beside {sys.executable}, PATH): "
        "install the package, or pass --exec"
    )


def under_home(executable: str) -> bool:
    """True when the program or the interpreter its #! line names lives in a home directory."""
    paths = [executable, os.path.realpath(executable)]
    try:
        with open(executable, "rb") as script:
            first = script.readline(4096)
    except OSError:
        first = b""
    if first.startswith(b"#!") and first[2:].split():
        interpreter = os.fsdecode(first[2:].split()[0])
        paths += [interpreter, os.path.realpath(interpreter)]
    return any(p.startswith(HOME_PREFIXES) for p in paths)


def exec_word(word: str) -> str:
    """One ExecStart= word: specifiers and variables escaped, quoted if it has blanks or quotes."""
    word = word.replace("%", "%%").replace("$", "$$")
    if any(c.isspace() or c in "\"'\\;" for c in word):
        return '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return word


def render_unit(
    executable: str,
    config_path: str = DEFAULT_CONFIG,
    writable: tuple[str, ...] = (),
    *,
    allow_pty: bool = False,
) -> str:
    """The unit with ExecStart, ProtectHome, extra `writable` directories and devices set."""
    text = unit_template()
    default_exec = f"ExecStart={TEMPLATE_EXEC} daemon --config {DEFAULT_CONFIG}"
    exec_line = f"ExecStart={exec_word(executable)} daemon --config {exec_word(config_path)}"
    text = text.replace(default_exec, exec_line)
    if under_home(executable):
        text = text.replace("\nProtectHome=yes\n", "\nProtectHome=read-only\n")
    extra = [d for d in writable if not d.startswith(SANDBOX_WRITABLE)]
    if extra:
        # ProtectSystem=strict leaves only listed paths writable; "-" tolerates a missing dir.
        paths = " ".join(exec_word(f"-{d}") for d in (DEFAULT_STATE_DIR, *extra))
        text = text.replace(f"ReadWritePaths=-{DEFAULT_STATE_DIR}", f"ReadWritePaths={paths}")
    if allow_pty:
        last_device = "DeviceAllow=char-video4linux rw\n"
        text = text.replace(
            last_device, f"{last_device}# Development only: the simulator's pty.\n{PTY_DEVICES}\n"
        )
    return text
