"""Every check the daemon's start makes on a configuration, without opening a device or moving.

`orbitar config check`, the daemon's start and a reload all call `preflight`, so a file that
`config check` passes is one the daemon starts with, and a refusal always names the key. What
the daemon tolerates (a serial adapter not plugged in yet, a camera that is missing, a recording
directory it cannot write) is a note, not an error: the daemon starts and says so.
"""

from __future__ import annotations

import grp
import os
import socket
import stat
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

from host.config import Config, load_config
from host.config_fields import ConfigError, shown
from host.outputs.udp import parse_destination
from host.service import wiring

UNIX_PATH_MAX_BYTES = 107  # sun_path holds 108 bytes on Linux, one of them the final NUL
ORTHONORMAL_NOTE_MIN = 1e-9  # entries moved less than this: the matrix was a rotation already
NO_FILE_SOURCES = ("sim", "none")
NETWORK_LINK_SCHEMES = ("socket", "rfc2217")  # pyserial URLs that name a host
# The transport names its options; the file names them in [link].
TRANSPORT_KEYS = {
    "url": "url",
    "baudrate": "baud",
    "dest_addr64": "xbee_address",
    "api_mode": "xbee_api_mode",
    "interface": "can_interface",
    "channel": "can_channel",
    "bitrate": "can_bitrate",
    "node_id": "node_id",
}


@dataclass
class Preflight:
    """What a configuration would meet at the daemon's start."""

    errors: list[str] = field(default_factory=list)  # the daemon refuses to start (exit 2)
    notes: list[str] = field(default_factory=list)  # the daemon starts and logs these

    @property
    def ok(self) -> bool:
        """True when the daemon would start."""
        return not self.errors


def check_file(path: str | Path, *, as_service: bool = False) -> tuple[Config | None, Preflight]:
    """Load a file and run the preflight on it; the config is None when it does not load."""
    try:
        config = load_config(path)
    except ConfigError as exc:
        return None, Preflight(errors=list(exc.problems))
    return config, preflight(config, as_service=as_service)


def preflight(config: Config, *, as_service: bool = False) -> Preflight:
    """Run every start check; `as_service`: permission problems are errors (we are the daemon)."""
    report = Preflight()
    _check_rig(config, report)
    _check_model(config, report)
    _check_link(config, report)
    _check_control(config, report, as_service)
    _check_outputs(config, report)
    _check_camera(config, report)
    _check_recording(config, report)
    return report


def _check_rig(config: Config, report: Preflight) -> None:
    """The rig file loads and the pose pipeline builds from it, as the frame loop does.

    The rig file's transforms are rotations already (host.rig refuses any other), so there is
    nothing to orthonormalise and no note to make.
    """
    try:
        rates = wiring.config_stream_rates(config)
        wiring.build_pose_source(config, rates, wiring.exposure_latency_ms(config))
        wiring.build_camera(config)
    except ValueError as exc:  # WiringError names the rig file and its key
        report.errors.append(_keyed(exc))


def _check_model(config: Config, report: Preflight) -> None:
    """The workpiece model loads (the daemon checks it even without a camera)."""
    try:
        wiring.build_model(config)
    except wiring.WiringError as exc:
        report.errors.append(_keyed(exc))


def _check_link(config: Config, report: Preflight) -> None:
    """The transport can be built; a device or host that is not there yet is only a note."""
    try:
        wiring.build_transport(config)
    except wiring.WiringError as exc:
        report.errors.append(_link_keyed(str(exc)))
        return
    link = config.link
    device, key = (
        (link.can_channel, "link.can_channel") if link.kind == "can" else (link.url, "link.url")
    )
    waits = "(the daemon waits for it)"
    if device.startswith("/dev/") and not os.path.exists(device):
        report.notes.append(f"{key} = {shown(device)}: no such device yet {waits}")
    url = urlsplit(device)
    if url.scheme in NETWORK_LINK_SCHEMES and url.hostname:
        problem = _resolve_problem(url.hostname, 0, passive=False)
        if problem:
            report.notes.append(f"{key} = {shown(device)}: {problem} {waits}")


def _link_keyed(message: str) -> str:
    """`[link]: transport (kind): OPTION …` as `link.KEY: OPTION …`."""
    text = message.removeprefix("[link]: ")
    _, sep, detail = text.partition("): ")
    option = detail.split(" ", 1)[0].split(":")[0].removeprefix("transport.") if sep else ""
    key = TRANSPORT_KEYS.get(option)
    return f"link.{key}: {detail}" if key else f"link: {text}"


def _check_control(config: Config, report: Preflight, as_service: bool) -> None:
    """The control socket can be bound where configured, and the TCP address resolves."""
    control = config.control
    path = control.socket_path
    size = len(os.fsencode(path))
    if size > UNIX_PATH_MAX_BYTES:
        report.errors.append(
            f"control.socket_path = {shown(path)}: {size} bytes, a Unix socket path holds at "
            f"most {UNIX_PATH_MAX_BYTES}"
        )
    elif not os.path.isabs(path):
        report.errors.append(f"control.socket_path = {shown(path)}: must be an absolute path")
    else:
        _check_socket_place(Path(path), report, as_service)
    if control.socket_group:
        try:
            grp.getgrnam(control.socket_group)
        except KeyError:
            report.errors.append(
                f"control.socket_group = {shown(control.socket_group)}: no such group"
            )
    if control.tcp_enabled:
        problem = _resolve_problem(control.tcp_host, control.tcp_port, passive=True)
        if problem:
            report.errors.append(f"control.tcp_host = {shown(control.tcp_host)}: {problem}")


def _check_socket_place(path: Path, report: Preflight, as_service: bool) -> None:
    """The socket file is absent or a socket, and its directory exists or can be made."""
    key = f"control.socket_path = {shown(str(path))}"
    if path.exists() and not stat.S_ISSOCK(path.stat().st_mode):
        report.errors.append(f"{key}: exists and is not a socket")
        return
    ancestor = path.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        report.errors.append(f"{key}: {ancestor} is not a directory")
    elif not os.access(ancestor, os.W_OK | os.X_OK):
        problem = f"{key}: {ancestor} is not writable by uid {os.getuid()}"
        if as_service:
            report.errors.append(problem)
        else:
            report.notes.append(problem + " (fine if the service user may write there)")


def _check_outputs(config: Config, report: Preflight) -> None:
    """Tracking output receivers that do not resolve: the output starts without them (status)."""
    outputs = config.outputs
    for name, output in (("freed", outputs.freed), ("opentrackio", outputs.opentrackio)):
        if not output.enabled:
            continue
        for i, destination in enumerate(output.destinations):
            host, port = parse_destination(destination)
            problem = _resolve_problem(host, port, passive=False)
            if problem:
                key = f"outputs.{name}.destinations[{i}] = {shown(destination)}"
                report.notes.append(f"{key}: {problem} (the output is not started; see status)")


def _check_camera(config: Config, report: Preflight) -> None:
    """A camera file or device that is missing: the daemon publishes poses without frames."""
    source = config.camera.source
    if isinstance(source, int):
        device = f"/dev/video{source}"
        if not os.path.exists(device):
            report.notes.append(f"camera.source = {source}: {device} does not exist (no frames)")
        return
    if source.lower() in NO_FILE_SOURCES or "://" in source:
        return
    if not os.path.exists(source):
        report.notes.append(f"camera.source = {shown(source)}: no such file (no frames)")


def _check_recording(config: Config, report: Preflight) -> None:
    """A recording directory the daemon cannot write: it runs without recording."""
    rec = config.recording
    if not rec.enabled:
        return
    ancestor = Path(rec.dir)
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        report.notes.append(
            f"recording.dir = {shown(rec.dir)}: {ancestor} is not a writable directory for uid "
            f"{os.getuid()} (the daemon starts without recording)"
        )


def _keyed(exc: Exception) -> str:
    """A wiring error as a problem line: its `[section]: ` prefix becomes the section's key."""
    text = str(exc)
    if text.startswith("[") and "]: " in text:
        section, _, rest = text[1:].partition("]: ")
        return f"{section}: {rest}"
    return text


def _resolve_problem(host: str, port: int, *, passive: bool) -> str | None:
    """Why `host` does not resolve, or None (DNS answers within the resolver's own timeout)."""
    flags = socket.AI_PASSIVE if passive else 0
    kind = socket.SOCK_STREAM if passive else socket.SOCK_DGRAM
    try:
        socket.getaddrinfo(host or None, port, type=kind, flags=flags)
    except (OSError, UnicodeError) as exc:
        return f"cannot resolve: {exc}"
    return None
