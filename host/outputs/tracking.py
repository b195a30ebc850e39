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
        """(Re)open the outputs as `config` says; one that cannot open leaves the running one."""
        self.errors = {}
        outputs = config.outputs
        freed = FreedSender(outputs.freed) if outputs.freed.enabled else None
        self.freed = await self._replace("freed", self.freed, freed)
        otio = None
        if outputs.opentrackio.enabled:
            from host.service.wiring import build_camera, rig_spec  # wiring imports the daemon

            fps = rig_spec(config).camera.fps
            otio = OpenTrackIOSender(outputs.opentrackio, build_camera(config), fps)
        self.opentrackio = await self._replace("opentrackio", self.opentrackio, otio)

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
            entry: dict[str, Any] | None = None if sender is None else dict(sender.stats())
            if entry is not None and name == "freed":
                entry["held_unhomed"] = self.freed_held
            if name in self.errors:  # not started, or the running one kept after a reload
                entry = {**(entry or {}), "error": self.errors[name]}
            result[name] = entry
        return result

    async def _replace(self, name: str, old: Any, new: Any) -> Any:
        """Open `new` before closing `old`; if it cannot open (an OS error: unresolvable host,
        no route), log it and keep `old` running, which is None at the first start."""
        if new is not None:
            try:
                await new.start()
            except OSError as exc:
                self.errors[name] = str(exc)
                log.error("output not started", extra={"kv": {"output": name, "error": exc}})
                return old
        if old is not None:
            old.close()
        return new
