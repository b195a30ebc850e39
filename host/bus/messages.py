"""Key expressions and msgpack payloads of the bus (docs/BUS.md): one place for both sides.

Every payload is a msgpack map with `v` (this format's version) and `rig`; times are host
monotonic nanoseconds (`t_ns`, meaningful on the rig PC only) and UTC nanoseconds (`t_unix_ns`).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import Any

import msgpack
import numpy as np

from host.control.api import PoseSample
from host.outputs.wallclock import monotonic_to_unix_ns

VERSION = 1
ROOT = "orbitar"
TOPICS = ("pose", "state", "stats", "event")  # published
QUERIES = ("status", "rig")  # answered
ALIVE = "alive"  # liveliness token


def key(rig: str, leaf: str) -> str:
    """`orbitar/<rig>/<leaf>`; rig may be `*` in a subscriber's selector."""
    return f"{ROOT}/{rig}/{leaf}"


def rig_of(key_expr: str) -> str:
    """The rig chunk of `orbitar/<rig>/…`."""
    parts = key_expr.split("/")
    return parts[1] if len(parts) > 2 and parts[0] == ROOT else ""


def _plain(value: Any) -> Any:
    """msgpack's fallback: numpy values, enums and anything else as plain types."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, set | frozenset | tuple):
        return list(value)
    return str(value)


def pack(rig: str, body: Mapping[str, Any]) -> bytes:
    """A versioned payload."""
    return bytes(msgpack.packb({"v": VERSION, "rig": rig, **body}, default=_plain))


def unpack(payload: bytes) -> dict[str, Any]:
    """A payload as a map; ValueError for bytes that are not one of ours."""
    try:
        data = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except (ValueError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as exc:
        raise ValueError(f"not msgpack: {exc}") from None
    if not isinstance(data, dict) or "v" not in data:
        raise ValueError("not a versioned map")
    return data


def pose_body(sample: PoseSample) -> dict[str, Any]:
    """A registered camera pose, as the control socket's pose event plus the wall-clock time."""
    body = sample.to_dict()
    body["t_unix_ns"] = monotonic_to_unix_ns(sample.t_ns)
    return body


def stamped(body: Mapping[str, Any], t_ns: int) -> dict[str, Any]:
    """`body` with the wall-clock time of host monotonic instant t_ns."""
    return {**body, "t_ns": t_ns, "t_unix_ns": monotonic_to_unix_ns(t_ns)}
