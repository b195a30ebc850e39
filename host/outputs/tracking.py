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
        self.freed_held = 0  # poses FreeD did not send: not homed (FreeD has no field to say so)

    async def start(self, config: Config) -> None:
        """(Re)open the outputs as `config` says."""
        self.close()
        self.errors = {}
        outputs = config.outputs
        if outputs.freed.enabled:
            self.freed = await self._open("freed", FreedSender(outputs.freed))
        if outputs.opentrackio.enabled:
            from host.service.wiring import build_camera  # wiring imports the daemon: no cycle

            sender = OpenTrackIOSender(outputs.opentrackio, build_camera(config), config.camera.fps)
            self.opentrackio = await self._open("opentrackio", sender)

    def send(self, sample: PoseSample) -> None:
        """One registered pose to every open output; FreeD only once the trolley is homed."""
        if self.freed is not None:
            if sample.homed:
                self.freed.send(sample.T_w_c)
            else:
                self.freed_held += 1
        if self.opentrackio is not None:
            self.opentrackio.send(sample)  # its tracker status says "not homed"

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
                if name == "freed":
                    result[name]["held_unhomed"] = self.freed_held
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
