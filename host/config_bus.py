"""`[bus]`: this rig on an Eclipse Zenoh bus, read-only, beside the control socket (docs/BUS.md)."""

from __future__ import annotations

import re
import socket
from dataclasses import dataclass
from typing import Any

from host.config_fields import spec

BUS_MODES = ("peer", "client")
RIG_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")
# Zenoh locators: protocol/address (tcp/127.0.0.1:7447, tcp/[::1]:7447, unixsock-stream/PATH)
ENDPOINT_RE = re.compile(r"^(tcp|udp|tls|quic|ws|unixsock-stream)/\S+$")


def parse_endpoint(value: Any) -> str:
    """A Zenoh endpoint such as "tcp/127.0.0.1:7447"."""
    if not isinstance(value, str) or not ENDPOINT_RE.match(value):
        raise ValueError('expected a Zenoh endpoint such as "tcp/127.0.0.1:7447"')
    return value


def parse_rig_id(value: Any) -> str:
    """Empty (the host name) or one key-expression chunk: letters, digits, '_', '.', '-'."""
    if not isinstance(value, str):
        raise ValueError("expected a string")
    if value and not RIG_ID_RE.match(value):
        raise ValueError("letters, digits, '_', '.' and '-' only (it becomes a key chunk)")
    return value


@dataclass(frozen=True)
class BusConfig:
    """Zenoh session: mode, endpoints and scouting; what this rig is called on the bus."""

    enabled: bool = spec(False, doc="switch this part on")
    rig_id: str = spec("", parse=parse_rig_id, doc="this rig's name on the bus (empty: host name)")
    mode: str = spec("peer", choices=BUS_MODES, doc='"peer" (no router needed) or "client"')
    listen: tuple[str, ...] = spec(
        (), parse=parse_endpoint, each=True, doc='endpoints to listen on, e.g. "tcp/0.0.0.0:7447"'
    )
    connect: tuple[str, ...] = spec(
        (), parse=parse_endpoint, each=True, doc="endpoints to connect to (peers or zenohd)"
    )
    scouting: bool = spec(
        False, doc="multicast scouting to find peers by itself (224.0.0.224:7446)"
    )
    stats_interval_s: float = spec(1.0, lo=0.05, hi=3600.0, doc="link statistics period")


def rig_name(config: BusConfig) -> str:
    """The configured rig id, or this host's name made into a valid key chunk."""
    if config.rig_id:
        return config.rig_id
    name = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname()).strip("-.")
    return name[:63] or "rig"


def bus_problems(config: BusConfig) -> list[str]:
    """Rules across keys."""
    if config.enabled and config.mode == "client" and not config.connect:
        return ['bus.connect: a "client" session needs at least one endpoint (a zenohd router)']
    return []
