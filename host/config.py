"""The daemon's configuration: one TOML file, validated on load into frozen dataclasses.

The built-in default is the paper's rig. Degrees appear only in the file (keys ending `_deg`);
the dataclasses hold radians. Every problem in a file is collected and reported at once as a
`ConfigError` naming the dotted key, the offending value and the reason.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import stat
import tomllib
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from host.config_bus import BusConfig, bus_problems
from host.config_fields import (
    ConfigError,
    check_text,
    deepest_nesting,
    parse_auto_ms,
    parse_destination,
    parse_mode,
    parse_regex,
    parse_source,
    parse_vector3,
    shown,
    spec,
    toml_key,
)
from host.config_opentrackio import OpenTrackIOConfig, opentrackio_problems
from host.config_rig import RigConfig
from host.config_ui import UiConfig, ui_problems

LINK_KINDS = ("serial", "xbee", "can")
LOG_LEVELS = ("debug", "info", "warning", "error", "critical")
MIN_TOKEN_CHARS = 16  # control tokens: long enough that guessing through hello is hopeless
XBEE_ADDRESS_RE = re.compile(r"^[0-9A-Fa-f]{16}$")
CONFIG_MAX_BYTES = 4 << 20  # the default file is ~10 kB; a rig with thousands of segments fits


@dataclass(frozen=True)
class LinkConfig:
    """How the host reaches the controller."""

    kind: str = spec(
        "serial",
        choices=LINK_KINDS,
        doc="serial (a UART), xbee (XBee API frames over a UART) or can (python-can)",
    )
    url: str = spec(
        "/dev/ttyUSB0", doc="serial device or URL, e.g. /dev/ttyUSB0 or socket://127.0.0.1:5555"
    )
    baud: int = spec(115200, lo=1200, hi=4_000_000, doc="UART bit rate")
    xbee_address: str = spec(
        "000000000000FFFF",
        parse=parse_regex(XBEE_ADDRESS_RE, "expected 16 hex digits"),
        doc="64-bit address of the controller's XBee, 16 hex digits",
    )
    xbee_api_mode: int = spec(2, choices=(1, 2), doc="XBee API mode: 1 (plain) or 2 (escaped)")
    can_interface: str = spec("slcan", doc="python-can interface name, e.g. socketcan or slcan")
    can_channel: str = spec("/dev/ttyACM0", doc="python-can channel, e.g. can0 or /dev/ttyACM0")
    can_bitrate: int = spec(500_000, lo=10_000, hi=1_000_000, doc="CAN bit rate, bit/s")
    node_id: int = spec(1, lo=1, hi=127, doc="controller node id on the CAN bus, 1..127")
    heartbeat_ms: int = spec(200, lo=10, hi=10_000, doc="host heartbeat period")
    reconnect_max_s: float = spec(
        10.0, lo=0.1, hi=3600.0, doc="longest wait between reconnect attempts"
    )


STAMP_MODES = ("steady", "as-delivered")


@dataclass(frozen=True)
class CameraConfig:
    """Where frames come from (resolution, rate and intrinsics are the rig file's)."""

    source: str | int = spec(
        "sim", parse=parse_source, doc='"sim", a device index, a video file or a URL'
    )
    stamps: str = spec(
        "steady",
        choices=STAMP_MODES,
        doc="\"steady\": each frame's stamp is put on the camera's fitted frame clock (a "
        'free-running camera\'s delivery jitter taken out, host.frames.stamps); "as-delivered": '
        "each frame keeps the stamp it came with",
    )


@dataclass(frozen=True)
class RegistrationConfig:
    """How far back the pose buffer reaches, and how long a frame waits for its samples."""

    horizon_ms: float = spec(
        2000.0, lo=10.0, hi=600_000.0, doc="how much pose history the buffer keeps"
    )
    frame_wait_ms: float | str = spec(
        "auto",
        parse=parse_auto_ms,
        doc='longest a frame waits for the samples of its exposure: "auto" (the link\'s, '
        "serial 30, xbee 150, can 20) or ms; 0 registers each frame as it arrives",
    )


@dataclass(frozen=True)
class FreedConfig:
    """FreeD D1 output; the axis mapping is a yaw and an origin of FreeD's frame in our world."""

    enabled: bool = spec(False, doc="switch this part on")
    destinations: tuple[str, ...] = spec(
        ("127.0.0.1:40000",), parse=parse_destination, each=True, doc='UDP "host:port" receivers'
    )
    camera_id: int = spec(1, lo=0, hi=255, doc="FreeD camera id byte")
    origin_mm: tuple[float, float, float] = spec(
        (0.0, 0.0, 0.0), parse=parse_vector3, doc="FreeD origin in our world frame"
    )
    yaw_rad: float = spec(
        0.0,
        key="yaw_deg",
        deg=True,
        lo=-360.0,
        hi=360.0,
        doc="FreeD frame turned about world z by this angle (see docs/FREED.md)",
    )
    zoom: int = spec(0, lo=0, hi=0xFFFFFF, doc="raw FreeD zoom value (fixed-focus lens)")
    focus: int = spec(0, lo=0, hi=0xFFFFFF, doc="raw FreeD focus value")


@dataclass(frozen=True)
class OutputsConfig:
    """Every output of the daemon."""

    freed: FreedConfig = field(default_factory=FreedConfig)
    opentrackio: OpenTrackIOConfig = field(default_factory=OpenTrackIOConfig)


@dataclass(frozen=True)
class ControlConfig:
    """The control socket and its optional TCP listener."""

    socket_path: str = spec("/run/orbitar/control.sock", doc="Unix control socket")
    socket_mode: int = spec(0o660, parse=parse_mode, doc="permissions of the socket file")
    socket_group: str = spec("", doc="group owning the socket file (empty: the daemon's group)")
    tcp_enabled: bool = spec(False, doc="also listen on TCP (needs a token in the hello request)")
    tcp_host: str = spec("127.0.0.1", doc="TCP listen address")
    tcp_port: int = spec(7431, lo=0, hi=65535, doc="TCP listen port")
    operator_token: str = spec("", doc="TCP token granting motion commands")
    viewer_token: str = spec("", doc="TCP token granting read-only access")
    queue_max: int = spec(
        256, lo=1, hi=100_000, doc="events buffered per subscriber before the oldest are dropped"
    )
    max_unix_connections: int = spec(16, lo=1, hi=1000, doc="clients at once on the Unix socket")
    max_tcp_connections: int = spec(32, lo=1, hi=1000, doc="clients at once on TCP")
    hello_timeout_s: float = spec(
        10.0, lo=0.1, hi=3600.0, doc="a TCP client without a successful hello is cut off after"
    )
    idle_timeout_s: float = spec(
        600.0,
        lo=1.0,
        hi=86400.0,
        doc="a client sending nothing and subscribed to nothing is cut off after",
    )
    client_buffer_kb: int = spec(
        2048,
        lo=256,
        hi=1_048_576,
        doc="replies queued for a client that does not read before it is cut off",
    )
    stall_timeout_s: float = spec(
        30.0, lo=0.1, hi=3600.0, doc="a client whose replies do not drain is cut off after"
    )


@dataclass(frozen=True)
class RecordingConfig:
    """What the daemon records and how much it keeps."""

    enabled: bool = spec(False, doc="switch this part on")
    dir: str = spec("/var/lib/orbitar/recordings", doc="recording directory")
    rotate_mb: float = spec(64.0, lo=0.001, hi=100_000.0, doc="start a new file above this size")
    keep_files: int = spec(10, lo=1, hi=100_000, doc="recording files kept, oldest deleted first")
    include_frames: bool = spec(False, doc="also record JPEG frames")


@dataclass(frozen=True)
class LogConfig:
    """Logging threshold."""

    level: str = spec("info", choices=LOG_LEVELS, doc="debug, info, warning, error or critical")


@dataclass(frozen=True)
class SystemdConfig:
    """Service manager integration."""

    ready_grace_s: float = spec(
        15.0, lo=0.0, hi=3600.0, doc="report READY=1 after this long even if the link is not up"
    )
    status_interval_s: float = spec(
        5.0, lo=0.1, hi=3600.0, doc="period of STATUS= updates to systemd"
    )


@dataclass(frozen=True)
class Config:
    """The whole configuration."""

    link: LinkConfig = field(default_factory=LinkConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    outputs: OutputsConfig = field(default_factory=OutputsConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    bus: BusConfig = field(default_factory=BusConfig)
    log: LogConfig = field(default_factory=LogConfig)
    systemd: SystemdConfig = field(default_factory=SystemdConfig)
    ui: UiConfig = field(default_factory=UiConfig)


def load_config(path: str | Path) -> Config:
    """Read and validate a TOML file; ConfigError lists every problem."""
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer (no effect on a regular file).
        with os.fdopen(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as file:
            if not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
                raise ConfigError([f"{path}: not a regular file"])
            data = file.read(CONFIG_MAX_BYTES + 1)  # bounded: /dev/zero or a huge file is refused
        if len(data) > CONFIG_MAX_BYTES:
            raise ConfigError([f"{path}: larger than {CONFIG_MAX_BYTES} bytes"])
        text = data.decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError([f"{path}: cannot read: {exc}"]) from exc
    return loads_config(text)


def loads_config(text: str) -> Config:
    """Validate TOML text into a Config."""
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"TOML syntax: {exc}"]) from exc
    except RecursionError as exc:  # tomllib recurses once per nested array or inline table
        key, depth = deepest_nesting(text)
        reason = f"arrays or inline tables nested {depth} deep, too deep to read"
        raise ConfigError([f"{key or 'TOML'}: {reason}"]) from exc
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise ConfigError([f"TOML value: {exc}"]) from exc
    return config_from_dict(table)


def config_from_dict(table: Mapping[str, Any]) -> Config:
    """Validate a parsed TOML table into a Config."""
    errors: list[str] = []
    config = _build(Config, table, "", errors)
    errors += _cross_checks(config, table)
    if errors:
        raise ConfigError(errors)
    return typing.cast(Config, config)


def _build(cls: type, table: Mapping[str, Any], prefix: str, errors: list[str]) -> Any:
    """Build dataclass `cls` from `table`, appending problems to `errors`."""
    hints = typing.get_type_hints(cls)
    fields = {f.metadata.get("key") or f.name: f for f in dataclasses.fields(cls)}
    for key in table:
        if key not in fields:
            known = ", ".join(sorted(fields))
            errors.append(f"{prefix}{toml_key(key)}: unknown key (known: {known})")
    values: dict[str, Any] = {}
    for key, fld in fields.items():
        if key in table:
            converted = _convert(hints[fld.name], fld, table[key], prefix + key, errors)
            if converted is not None:
                values[fld.name] = converted
    return cls(**values)


def _convert(
    hint: Any, fld: dataclasses.Field[Any], value: Any, key: str, errors: list[str]
) -> Any:
    """Check one value against its field; None (and a recorded error) when it is wrong."""
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            errors.append(f"{key} = {shown(value)}: expected a table")
            return None
        return _build(typing.cast(type, hint), value, key + ".", errors)
    if origin is tuple and dataclasses.is_dataclass(typing.get_args(hint)[0]):
        return _convert_table_array(typing.get_args(hint)[0], value, key, errors)
    if fld.metadata.get("each"):
        return _convert_list(fld, value, key, errors)
    try:
        return _check_scalar(hint, fld.metadata, value)
    except (ValueError, OverflowError) as exc:
        errors.append(f"{key} = {shown(value)}: {exc}")
        return None


def _convert_table_array(cls: Any, value: Any, key: str, errors: list[str]) -> Any:
    """An array of tables such as [[track.segments]]."""
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        errors.append(f"{key} = {shown(value)}: expected an array of tables")
        return None
    return tuple(_build(cls, v, f"{key}[{i}].", errors) for i, v in enumerate(value))


def _convert_list(fld: dataclasses.Field[Any], value: Any, key: str, errors: list[str]) -> Any:
    """A list whose items each pass the field's parser."""
    if not isinstance(value, list):
        errors.append(f"{key} = {shown(value)}: expected a list")
        return None
    out = []
    for i, item in enumerate(value):
        try:
            out.append(fld.metadata["parse"](item))
        except (ValueError, OverflowError) as exc:
            errors.append(f"{key}[{i}] = {shown(item)}: {exc}")
    return tuple(out)


def _check_scalar(hint: Any, meta: Mapping[str, Any], value: Any) -> Any:
    """Type, choice and range check of a single value; ValueError names the reason."""
    if meta.get("parse"):
        return meta["parse"](value)
    value = _check_type(hint, value)
    if meta.get("choices") is not None and value not in meta["choices"]:
        raise ValueError(f"must be one of {', '.join(map(repr, meta['choices']))}")
    lo, hi = meta.get("lo"), meta.get("hi")
    if (lo is not None and value < lo) or (hi is not None and value > hi) or value != value:
        raise ValueError(f"out of range [{lo}, {hi}]")
    return math.radians(value) if meta.get("deg") else value


def _check_type(hint: Any, value: Any) -> Any:
    """Accept `value` if it has the type of `hint` (an int is a fine float; a bool is neither)."""
    if hint is bool:
        if not isinstance(value, bool):
            raise ValueError("expected true or false")
        return value
    if isinstance(value, bool):
        raise ValueError(f"expected {hint.__name__}, got a boolean")
    if hint is float and isinstance(value, int | float):
        return float(value)  # OverflowError for an int beyond float: reported by the caller
    if not isinstance(value, hint):
        raise ValueError(f"expected {hint.__name__}, got {type(value).__name__}")
    if isinstance(value, str):
        check_text(value)
    return value


def _cross_checks(config: Config, table: Mapping[str, Any]) -> list[str]:
    """Rules that span several keys."""
    errors = []
    errors += opentrackio_problems(config.outputs.opentrackio)
    errors += bus_problems(config.bus)
    if config.control.tcp_enabled and not config.control.operator_token:
        errors.append("control.operator_token: required when control.tcp_enabled = true")
    for key in ("operator_token", "viewer_token"):
        if 0 < (n := len(getattr(config.control, key))) < MIN_TOKEN_CHARS:
            hint = "python3 -c 'import secrets; print(secrets.token_urlsafe(24))' makes one"
            errors.append(f"control.{key}: {n} characters, need {MIN_TOKEN_CHARS} or more ({hint})")
    errors += ui_problems(config.ui)
    return errors


def default_config_text() -> str:
    """The commented default file, generated from the dataclasses; it loads to `Config()`."""
    lines = ["# Orbitar daemon configuration. Defaults: the paper's rig. Angles in degrees.", ""]
    _emit_section(Config(), "", lines)
    return "\n".join(lines).rstrip() + "\n"


def _emit_section(obj: Any, prefix: str, lines: list[str]) -> None:
    """Append `[prefix]` and the commented keys of dataclass instance `obj`."""
    nested = []
    if prefix:
        lines += [f"[{prefix}]", f"# {type(obj).__doc__}"]
    for fld in dataclasses.fields(obj):
        value = getattr(obj, fld.name)
        if dataclasses.is_dataclass(value):
            nested.append((value, f"{prefix}.{fld.name}".lstrip(".")))
        elif fld.name in _TABLE_ARRAY_EXAMPLES:
            lines.append(_TABLE_ARRAY_EXAMPLES[fld.name])
        else:
            lines.append(f"# {fld.metadata.get('doc', '')}")
            lines.append(f"{fld.metadata.get('key') or fld.name} = {_toml_value(fld, value)}")
    lines.append("")
    for value, name in nested:
        _emit_section(value, name, lines)


_TABLE_ARRAY_EXAMPLES: dict[str, str] = {}


def _toml_value(fld: dataclasses.Field[Any], value: Any) -> str:
    """A default value written as TOML (radians back to degrees, modes in octal)."""
    if fld.metadata.get("deg"):
        return repr(round(math.degrees(value), 9))
    if fld.name == "socket_mode":
        return f'"{value:04o}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml_value(fld, v) for v in value) + "]"
    return repr(value)
