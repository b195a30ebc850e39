"""The operator station: the live AR view, touch controls and status in a browser (issue 12)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from host.service.daemon import Daemon
    from host.station.server import Station


def pose_feed(controller: object) -> Any:
    """The controller's PoseFeed sink (raw and corrected track position), or None."""
    from host.registration.track_feed import PoseFeed

    sinks = getattr(controller, "sinks", ())
    return next((s for s in sinks if isinstance(s, PoseFeed)), None)


def attach_station(daemon: Daemon) -> Station:
    """A station on the daemon's ops, fed by its frame loop (the daemon starts and closes it)."""
    from host.frames.loop import FrameLoop, frame_loop_status
    from host.station.server import Station

    feed = pose_feed(daemon.controller)

    def ghost_offset_mm() -> float | None:
        raw, corrected = getattr(feed, "raw_s_mm", None), getattr(feed, "s_mm", None)
        if raw is None or corrected is None or getattr(feed, "chain", None) is None:
            return None
        return float(raw) - float(corrected)

    def frames() -> dict[str, Any]:
        return frame_loop_status(daemon.frame_loop) or {"source": {"kind": "none"}}

    def hall() -> list[dict[str, Any]] | None:
        return daemon.bus.hall() if daemon.bus is not None else None

    station = Station(daemon.config, daemon.server.context, frames, ghost_offset_mm, hall)
    loop = getattr(daemon.frame_loop, "loop", None)
    if isinstance(loop, FrameLoop):
        loop.outputs.append(station.on_registration)
    return station
