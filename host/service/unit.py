"""The systemd unit shipped with the package, rendered for a given executable and paths."""

from __future__ import annotations

from importlib import resources

UNIT_NAME = "orbitar.service"
DEFAULT_EXEC = "/usr/bin/orbitar"
DEFAULT_CONFIG = "/etc/orbitar/orbitar.toml"
DEFAULT_STATE_DIR = "/var/lib/orbitar"


def unit_template() -> str:
    """The unit file as shipped in host/data."""
    return resources.files("host").joinpath("data", UNIT_NAME).read_text(encoding="utf-8")


def render_unit(
    executable: str = DEFAULT_EXEC,
    config_path: str = DEFAULT_CONFIG,
    recording_dir: str | None = None,
) -> str:
    """The unit with ExecStart and the writable recording directory filled in."""
    text = unit_template()
    default_exec = f"ExecStart={DEFAULT_EXEC} daemon --config {DEFAULT_CONFIG}"
    text = text.replace(default_exec, f"ExecStart={executable} daemon --config {config_path}")
    if recording_dir and not recording_dir.startswith(DEFAULT_STATE_DIR):
        # ProtectSystem=strict leaves only listed paths writable; "-" tolerates a missing dir.
        extra = f"ReadWritePaths=-{DEFAULT_STATE_DIR} -{recording_dir}"
        text = text.replace(f"ReadWritePaths=-{DEFAULT_STATE_DIR}", extra)
    return text
