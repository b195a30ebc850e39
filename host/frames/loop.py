"""The frame loop: capture off the event loop, keep only the newest frame, register it.

A capture thread reads the source as fast as it delivers and puts each frame into a one-slot
mailbox; a frame still waiting when the next arrives is dropped and counted, so a slow
registration never builds a queue and latency stays bounded. The event loop takes the newest
frame, runs the (CPU-bound) processing in a worker thread and hands the result to the outputs.
The loop never waits on the link, and the link never waits on it.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from host.frames.sources import Frame, FrameSource

log = logging.getLogger(__name__)

ResultT = TypeVar("ResultT")
LATENCY_WINDOW = 512  # frames kept for the latency percentiles


@dataclass
class FrameLoopStats:
    """Counters and latency of the frame loop."""

    captured: int = 0
    processed: int = 0
    dropped: int = 0
    failed: int = 0
    latencies_ms: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))

    def latency_ms(self, quantile: float) -> float:
        """A quantile of the recent exposure-to-result latency (nan before any frame)."""
        if not self.latencies_ms:
            return float("nan")
        ordered = sorted(self.latencies_ms)
        return ordered[min(len(ordered) - 1, int(quantile * len(ordered)))]


class FrameLoop(Generic[ResultT]):
    """Reads a source in a thread, processes the newest frame, fans results out."""

    def __init__(
        self,
        source: FrameSource,
        process: Callable[[Frame], ResultT],
        outputs: list[Callable[[ResultT], None]] | None = None,
    ) -> None:
        self.source = source
        self.process = process
        self.outputs = list(outputs or [])
        self.stats = FrameLoopStats()
        self._slot: Frame | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ended = False
        self._wake: tuple[asyncio.AbstractEventLoop, asyncio.Event] | None = None

    async def run(self, max_frames: int | None = None) -> None:
        """Run until the source ends, `stop()` is called or max_frames were processed."""
        loop = asyncio.get_running_loop()
        wake = asyncio.Event()
        self._wake = (loop, wake)
        thread = threading.Thread(
            target=self._capture, args=(loop, wake), name="frame-capture", daemon=True
        )
        thread.start()
        try:
            while max_frames is None or self.stats.processed < max_frames:
                wake.clear()  # before taking, so a frame arriving meanwhile still wakes us
                frame = self._take()
                if frame is None:
                    if self._ended or self._stop.is_set():
                        break
                    await wake.wait()
                    continue
                await self._handle(frame)
        finally:
            self._stop.set()
            await asyncio.to_thread(thread.join, 5.0)

    def status(self) -> dict[str, Any]:
        """Counters, latency and the source's own state (a file's end, a lost device)."""
        describe = getattr(self.source, "describe", None)
        p50, p95 = self.stats.latency_ms(0.5), self.stats.latency_ms(0.95)
        return {
            "captured": self.stats.captured,
            "processed": self.stats.processed,
            "dropped": self.stats.dropped,
            "failed": self.stats.failed,
            "source_ended": self._ended,
            "latency_ms_p50": None if math.isnan(p50) else round(p50, 2),
            "latency_ms_p95": None if math.isnan(p95) else round(p95, 2),
            "source": describe() if callable(describe) else self._plain_source(),
        }

    def _plain_source(self) -> dict[str, Any]:
        """What can be said of a source that does not describe itself."""
        state = "ended" if self._ended else "running"
        return {"source": type(self.source).__name__, "kind": "camera", "state": state}

    def stop(self) -> None:
        """Ask the loop to end after the frame in hand (callable from any thread)."""
        self._stop.set()
        if self._wake is not None:
            loop, wake = self._wake
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(wake.set)

    async def _handle(self, frame: Frame) -> None:
        """Process one frame off the loop and deliver its result."""
        try:
            result = await asyncio.to_thread(self.process, frame)
        except Exception:
            self.stats.failed += 1
            log.exception("frame %d failed to register", frame.index)
            return
        self.stats.processed += 1
        self.stats.latencies_ms.append((time.monotonic_ns() - frame.exposure_ns) / 1e6)
        for output in self.outputs:
            try:
                output(result)
            except Exception:
                log.exception("frame output %r failed", output)

    def _take(self) -> Frame | None:
        """Empty the mailbox."""
        with self._lock:
            frame, self._slot = self._slot, None
        return frame

    def _capture(self, loop: asyncio.AbstractEventLoop, wake: asyncio.Event) -> None:
        """Capture thread: newest frame wins the mailbox."""
        try:
            while not self._stop.is_set():
                frame = self.source.read()
                if frame is None:
                    break
                with self._lock:
                    if self._slot is not None:
                        self.stats.dropped += 1
                    self._slot = frame
                    self.stats.captured += 1
                with contextlib.suppress(RuntimeError):  # loop closed while we read
                    loop.call_soon_threadsafe(wake.set)
        except Exception:
            log.exception("camera source failed")
        finally:
            self._ended = True
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(wake.set)


def frame_loop_status(owner: object) -> dict[str, Any] | None:
    """The status of the FrameLoop inside a daemon's pose loop, None when it has no camera."""
    loop = getattr(owner, "loop", None)
    return loop.status() if isinstance(loop, FrameLoop) else None
