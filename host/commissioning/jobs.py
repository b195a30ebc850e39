"""One commissioning run at a time inside the daemon: start, progress, cancel, result.

A run is an asyncio task. Its progress is a plain dict the run updates (phase, views, coverage),
read by `commissioning_status`; a client that disconnects does not stop it, `commissioning_cancel`
and any STOP or ESTOP do (`cancel_all` runs before the stop is sent, so the run can never command
a motion after the operator's stop). A cancelled or failed run writes nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)

Progress = dict[str, Any]
RunFn = Callable[[Progress], Coroutine[Any, Any, dict[str, Any]]]


class JobBusyError(RuntimeError):
    """Another run is in progress."""


@dataclass
class Job:
    """One run: its id, kind, progress, and the task doing it."""

    id: int
    kind: str
    progress: Progress
    task: asyncio.Task[dict[str, Any]]
    started_s: float = field(default_factory=time.monotonic)
    cancel_reason: str = ""

    def status(self) -> dict[str, Any]:
        """Plain values for the status op."""
        out: dict[str, Any] = {
            "id": self.id,
            "kind": self.kind,
            "elapsed_s": round(time.monotonic() - self.started_s, 2),
            "progress": dict(self.progress),
        }
        if not self.task.done():
            out["state"] = "running"
        elif self.task.cancelled():
            out["state"] = "cancelled"
            out["reason"] = self.cancel_reason or "cancelled"
        elif (exc := self.task.exception()) is not None:
            out["state"] = "error"
            out["error"] = f"{type(exc).__name__}: {exc}"
        else:
            out["state"] = "done"
            out["result"] = self.task.result()
        return out


@dataclass(frozen=True)
class Filmed:
    """The views a board run filmed, kept for a later run that may reuse them (the head
    calibration solves from the intrinsics run's views instead of filming the same plan)."""

    job: int
    kind: str
    board: dict[str, Any]  # the BoardSpec as given
    centre_mm: tuple[float, ...]  # the board centre the plan aimed at (world)
    stations_mm: tuple[float, ...]
    home_s_mm: float  # the zero the views' arc lengths were taken with
    views: tuple[Any, ...]  # host.commissioning.intrinsics_run.CapturedView


class JobBoard:
    """The daemon's commissioning runs (at most one running), and the last board filming."""

    def __init__(self) -> None:
        self._ids = itertools.count(1)
        self.current: Job | None = None
        self.filmed: Filmed | None = None

    def start(self, kind: str, run: RunFn) -> Job:
        """Start a run; JobBusyError while another one is running."""
        if self.current is not None and not self.current.task.done():
            raise JobBusyError(f"{self.current.kind} run {self.current.id} is still running")
        progress: Progress = {"phase": "starting"}
        task = asyncio.get_running_loop().create_task(run(progress))
        job = Job(next(self._ids), kind, progress, task)
        task.add_done_callback(lambda t: self._done(job))
        self.current = job
        return job

    def get(self, job_id: int | None = None) -> Job | None:
        """The current run (or the one with this id, if it is the current one)."""
        if self.current is None or (job_id is not None and self.current.id != job_id):
            return None
        return self.current

    def cancel_all(self, reason: str) -> bool:
        """Cancel the running run now (synchronously); True if there was one."""
        job = self.current
        if job is None or job.task.done():
            return False
        job.cancel_reason = reason
        job.task.cancel()
        return True

    async def aclose(self) -> None:
        """Cancel and await the running run (daemon shutdown)."""
        job = self.current
        if job is not None and not job.task.done():
            self.cancel_all("daemon stopping")
            with contextlib.suppress(BaseException):
                await job.task

    @staticmethod
    def _done(job: Job) -> None:
        """Log how a run ended."""
        if job.task.cancelled():
            log.info(
                "commissioning run cancelled",
                extra={"kv": {"id": job.id, "why": job.cancel_reason}},
            )
        elif job.task.exception() is not None:
            log.error(
                "commissioning run failed",
                extra={"kv": {"id": job.id, "error": job.task.exception()}},
            )
