"""Link backends behind one interface, chosen by name (see `base.Transport`).

    transport = create_transport("serial", url="/dev/ttyUSB0", baudrate=115200)
    transport = transport_from_config({"kind": "xbee", "url": "/dev/ttyUSB1", "dest_addr64": …})
    transport = transport_from_config({"url": "can://slcan/dev/ttyACM0?node_id=3"})
    transport = await open_transport(config)   # the same, opened

Bad options raise `TransportConfigError` naming the key and the reason.
"""

from __future__ import annotations

import inspect
import urllib.parse
from collections.abc import Mapping
from typing import Any

from host.transport.base import (
    FrameTooLargeError,
    Transport,
    TransportError,
    TransportState,
    TransportStats,
)
from host.transport.can import CanTransport
from host.transport.serial import SerialTransport
from host.transport.xbee import XBeeTransport

BACKENDS: dict[str, type[Transport]] = {
    "serial": SerialTransport,
    "xbee": XBeeTransport,
    "can": CanTransport,
}
# pyserial settings a serial-like backend passes through untouched.
SERIAL_PASSTHROUGH = frozenset(
    ("bytesize", "parity", "stopbits", "rtscts", "xonxoff", "dsrdtr", "exclusive")
)
# Integer-valued options that may arrive as strings from a URL query.
_INT_OPTIONS = frozenset(("baudrate", "api_mode", "node_id", "bitrate"))

__all__ = [
    "BACKENDS",
    "FrameTooLargeError",
    "Transport",
    "TransportConfigError",
    "TransportError",
    "TransportState",
    "TransportStats",
    "create_transport",
    "open_transport",
    "parse_url",
    "transport_from_config",
]


class TransportConfigError(ValueError):
    """A transport option is missing, unknown or bad; the message names it."""


def create_transport(kind: str, **options: Any) -> Transport:
    """Backend `kind` built from keyword options, checked before anything is opened."""
    backend = BACKENDS.get(kind)
    if backend is None:
        raise TransportConfigError(f"transport.kind: {kind!r} is not one of {sorted(BACKENDS)}")
    _check_keys(kind, backend, options)
    try:
        return backend(**options)
    except (ValueError, TypeError) as exc:
        raise TransportConfigError(f"transport ({kind}): {exc}") from exc


def transport_from_config(config: Mapping[str, Any]) -> Transport:
    """A transport from a config table: `kind` + options, or a `url` that implies the kind."""
    if not isinstance(config, Mapping):
        raise TransportConfigError(f"transport: expected a table, got {type(config).__name__}")
    options = dict(config)
    kind = options.pop("kind", None)
    if kind is None:
        if "url" not in options:
            raise TransportConfigError("transport: needs 'kind' or 'url'")
        kind, from_url = parse_url(str(options.pop("url")))
        options = {**from_url, **options}
    return create_transport(str(kind), **options)


async def open_transport(config: Mapping[str, Any]) -> Transport:
    """`transport_from_config` and open it; TransportError if the device is not there."""
    transport = transport_from_config(config)
    await transport.open()
    return transport


def parse_url(url: str) -> tuple[str, dict[str, Any]]:
    """Link URL → (kind, options).

    `/dev/…`, `socket://`, `rfc2217://`, `loop://` → serial; `xbee:///dev/ttyUSB0?dest_addr64=…`;
    `can://INTERFACE/CHANNEL?node_id=…`; any query parameter becomes an option.
    """
    parts = urllib.parse.urlsplit(url)
    query = {k: _coerce(k, v) for k, v in urllib.parse.parse_qsl(parts.query)}
    if parts.scheme == "xbee":
        return "xbee", {"url": parts.path, **query}
    if parts.scheme == "can":
        if not parts.netloc:
            raise TransportConfigError(f"transport.url: {url!r} names no CAN interface")
        return "can", {"interface": parts.netloc, "channel": parts.path.lstrip("/"), **query}
    return "serial", {"url": url}


def _coerce(key: str, value: str) -> Any:
    """URL query strings to ints where the option is an integer."""
    if key not in _INT_OPTIONS:
        return value
    try:
        return int(value, 0)
    except ValueError:
        raise TransportConfigError(f"transport.{key}: {value!r} is not an integer") from None


def _check_keys(kind: str, backend: type[Transport], options: Mapping[str, Any]) -> None:
    """Name the first missing or unknown option."""
    params = inspect.signature(backend.__init__).parameters
    named = {n for n, p in params.items() if n != "self" and p.kind is p.POSITIONAL_OR_KEYWORD}
    required = {n for n in named if params[n].default is inspect.Parameter.empty}
    for key in sorted(required - options.keys()):
        raise TransportConfigError(f"transport.{key}: required for {kind}")
    if kind == "can":
        return  # python-can interfaces take their own keyword arguments
    for key in sorted(options.keys() - named - SERIAL_PASSTHROUGH):
        known = sorted(named | SERIAL_PASSTHROUGH)
        raise TransportConfigError(f"transport.{key}: unknown option for {kind} (known: {known})")
