"""What the daemon hands the recording: raw link bytes, camera frames, and the file header.

The taps only pass references on (the writer's `write` queues and returns at once): the link tap
runs on the event loop inside the transport, the frame tap in the frame loop's worker thread,
where the frame is registered, so a JPEG is never encoded on the loop.
"""

from __future__ import annotations

import dataclasses
import enum
import socket
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from host.recording.writer import KIND_FRAME, KIND_LINK
from host.transport.base import ByteTap, Transport

if TYPE_CHECKING:
    from host.frames.registrar import Registration
    from host.frames.sources import Frame

RecordTap = Callable[[str, int, Any], object]  # kind, host time ns, data (the daemon's record)


def link_tap(record: RecordTap) -> ByteTap:
    """A transport tap writing every received chunk and sent frame as a `link` record."""

    def tap(direction: str, t_ns: int, data: bytes) -> None:
        record(KIND_LINK, t_ns, {"dir": direction, "bytes": data})

    return tap


def attach_link_tap(transport: Transport, record: RecordTap) -> Transport:
    """Record the raw bytes of `transport` through `record`; returns the transport."""
    transport.set_tap(link_tap(record))
    return transport


class FrameTap:
    """Wraps the registrar: each registered frame goes to the recording with its image.

    Runs where the registrar runs (a worker thread); the writer encodes the JPEG in its own
    thread when `include_frames` is on and drops the image otherwise.
    """

    def __init__(self, registrar: Callable[[Frame], Registration], record: RecordTap) -> None:
        self.registrar = registrar
        self.record = record

    def __call__(self, frame: Frame) -> Registration:
        """Register the frame, then record it (its exposure stamp, status and image)."""
        reg = self.registrar(frame)
        data = {
            "index": reg.index,
            "exposure_ns": reg.exposure_ns,
            "status": reg.status.value,
            "image": frame.image,
        }
        self.record(KIND_FRAME, reg.exposure_ns, data)
        return reg


def recording_header(config: Any, config_path: str | Path | None) -> dict[str, Any]:
    """Header fields naming what the daemon runs with: the config file's text and the values."""
    text = ""
    if config_path is not None:
        try:
            text = Path(config_path).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            text = f"# could not be read when the recording started: {exc}\n"
    return {
        "hostname": socket.gethostname(),
        "link_bytes": True,  # `link` records carry every byte: replay can re-run the link
        "config_path": str(config_path) if config_path is not None else None,
        "config_toml": text,  # "" when the daemon ran on the built-in defaults
        "config": plain(config),
    }


def header_source(
    fixed: dict[str, Any], controller: Any, calibration: Callable[[], Mapping[str, Any]]
) -> Callable[[], dict[str, Any]]:
    """Header fields for each new file, called in the writer thread as the file is opened.

    `fixed`, the time, the calibration in use now and the link's identity so far. A file
    started mid-session (rotation, a reload, a disk that came back) holds no IDENTIFY of its
    own: the header carries the controller's, so a replay of that file alone can still convert
    its samples. `controller` is the daemon's; anything without an identity gives None.
    """

    def header() -> dict[str, Any]:
        try:
            in_use: Any = plain(calibration())
        except Exception as exc:  # a header is never worth a lost recording
            in_use = {"error": f"{type(exc).__name__}: {exc}"}
        return {
            **fixed,
            "monotonic_ns": time.monotonic_ns(),
            "calibration": in_use,
            "link_identity": _identity(controller),
        }

    return header


def _identity(controller: Any) -> dict[str, Any] | None:
    """The IDENTIFY constants the controller link holds, as a plain dict (None before any)."""
    link = getattr(controller, "ctrl", controller)  # the daemon's adapter wraps the link's
    identity = getattr(link, "identity", None)
    if identity is None or not dataclasses.is_dataclass(identity):
        return None
    result: dict[str, Any] = plain(identity)
    return result


def plain(value: Any) -> Any:
    """Dataclasses, enums, tuples and paths as msgpack-ready dicts, lists and strings."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, enum.Enum):
        return plain(value.value)
    if value is None or isinstance(value, bool | int | float | str | bytes):
        return value
    return str(value)
