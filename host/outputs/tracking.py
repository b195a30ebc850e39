"""The daemon's camera-tracking outputs (FreeD, OpenTrackIO), opened and fed as one."""

from __future__ import annotations

import logging
from typing import Any

from host.config import Config
from host.control.api import PoseSample
from host.outputs.freed import FreedSender
from host.outputs.opentrackio import OpenTrackIOSender

log = logging.getLogger(__name__)


class TrackingOutputs:
    """Every enabled tracking output; one that cannot open is reported, never fatal."""

    def __init__(self) -> None:
        self.freed: FreedSender | None = None
        self.opentrackio: OpenTrackIOSender | None = None
        self.errors: dict[str, str] = {}  # output name → why it is not running

    async def start(self, config: Config) -> None:
        """(Re)open the outputs as `config` says."""
        self.close()
        self.errors = {}
        outputs = config.outputs
        if outputs.freed.enabled:
            self.freed = await self._open("freed", FreedSender(outputs.freed))
        if outputs.opentrackio.enabled:
            # wiring imports the daemon: no cycle; the camera and its rate are the rig file's
            from host.service.wiring import build_camera, rig_spec

            fps = rig_spec(config).camera.fps
            sender = OpenTrackIOSender(outputs.opentrackio, build_camera(config), fps)
            self.opentrackio = await self._open("opentrackio", sender)

    def send(self, sample: PoseSample) -> None:
        """One registered pose to every open output."""
        if self.freed is not None:
            self.freed.send(sample.T_w_c)
        if self.opentrackio is not None:
            self.opentrackio.send(sample)

    def close(self) -> None:
        """Close every output."""
        for sender in (self.freed, self.opentrackio):
            if sender is not None:
                sender.close()
        self.freed = self.opentrackio = None

    def stats(self) -> dict[str, Any]:
        """Per output: its counters, or why it is not running (None: not enabled)."""
        result: dict[str, Any] = {}
        for name, sender in (("freed", self.freed), ("opentrackio", self.opentrackio)):
            if sender is not None:
                result[name] = sender.stats()
            elif name in self.errors:
                result[name] = {"error": self.errors[name]}
            else:
                result[name] = None
        return result

    async def _open(self, name: str, sender: Any) -> Any:
        """Start a sender; on an OS error (unresolvable host, no route) log it and go without."""
        try:
            await sender.start()
        except OSError as exc:
            self.errors[name] = str(exc)
            log.error("output not started", extra={"kv": {"output": name, "error": exc}})
            return None
        return sender
