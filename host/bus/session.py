"""A Zenoh session from `[bus]`: peer or client mode, explicit endpoints, scouting on or off."""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

from host.config_bus import BusConfig


def zenoh_config(
    mode: str, listen: Sequence[str], connect: Sequence[str], scouting: bool
) -> zenoh.Config:
    """Zenoh's configuration for these settings (multicast scouting only when asked for).

    Timestamping is on because the state topic's publisher keeps its last sample for late
    subscribers (zenoh.ext's advanced publisher requires it).
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("timestamping/enabled", "true")
    config.insert_json5("scouting/multicast/enabled", json.dumps(scouting))
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return config


def open_session(config: BusConfig) -> zenoh.Session:
    """Open the session `[bus]` describes (blocking: call it off the event loop)."""
    return zenoh.open(zenoh_config(config.mode, config.listen, config.connect, config.scouting))
