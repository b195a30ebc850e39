"""The frame loop: capture off the event loop, register each frame once its samples are in.

A capture thread reads the source as fast as it delivers and hands each frame to the event
loop, which runs the (CPU-bound) processing in a worker thread and gives the result to the
outputs. When it takes a frame, older ones still waiting are dropped and counted, so a slow
registration never builds a queue and latency stays bounded.

A frame may wait for its samples (`ready`), at most `max_wait_s`: over a slow link (the XBee's
batches arrive 50–100 ms after their stamps) a frame registered on arrival is placed by
extrapolating old samples, and a tooth skip shows in it until a reading after the skip has
come in. Broadcast render engines delay the video to the tracking data for the same reason.
The link never waits on the loop; the loop waits on it only that long.
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

from host.frames.sources import Frame, FrameSource, describe_source

log = logging.getLogger(__name__)

ResultT = TypeVar("ResultT")
LATENCY_WINDOW = 512  # frames kept for the latency percentiles
PENDING_LIMIT = 32  # frames held for their samples; past it the oldest is dropped
WAIT_POLL_S = 0.002  # how often a held frame's samples are looked for (they come in on the link)


@dataclass
class FrameLoopStats:
    """Counters and latency of the frame loop."""

    captured: int = 0
    processed: int = 0
    dropped: int = 0
    failed: int = 0
    timed_out: int = 0  # registered after max_wait_s without all their samples (a late link)
    latencies_ms: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))

    def latency_ms(self, quantile: float) -> float:
        """A quantile of the recent exposure-to-result latency (nan before any frame)."""
        if not self.latencies_ms:
            return float("nan")
        ordered = sorted(self.latencies_ms)
        return ordered[min(len(ordered) - 1, int(quantile * len(ordered)))]


class FrameLoop(Generic[ResultT]):
    """Reads a source in a thread, processes the frames as they become due, fans results out.

    `ready(frame)`: whether the samples its pose is made from have arrived; without it every
    frame is ready when captured, and the newest one wins.
    """

    def __init__(
        self,
        source: FrameSource,
        process: Callable[[Frame], ResultT],
        outputs: list[Callable[[ResultT], None]] | None = None,
        ready: Callable[[Frame], bool] | None = None,
        max_wait_s: float = 0.0,
    ) -> None:
        self.source = source
        self.process = process
        self.outputs = list(outputs or [])
        self.ready = ready
        self.max_wait_ns = round(max_wait_s * 1e9)
        self.stats = FrameLoopStats()
        self._pending: deque[tuple[Frame, int]] = deque()  # (frame, captured at)
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
                frame = self._take(time.monotonic_ns())
                if frame is None:
                    if self._stop.is_set() or (self._ended and not self._pending):
                        break
                    if self._pending:  # held for samples, which no event announces
                        with contextlib.suppress(TimeoutError):
                            await asyncio.wait_for(wake.wait(), WAIT_POLL_S)
                    else:
                        await wake.wait()
                    continue
                await self._handle(frame)
        finally:
            self._stop.set()
            await asyncio.to_thread(thread.join, 5.0)

    def status(self) -> dict[str, Any]:
        """Counters, latency and the source's own state (a file's end, a lost device)."""
        p50, p95 = self.stats.latency_ms(0.5), self.stats.latency_ms(0.95)
        return {
            "captured": self.stats.captured,
            "processed": self.stats.processed,
            "dropped": self.stats.dropped,
            "failed": self.stats.failed,
            "timed_out": self.stats.timed_out,
            "source_ended": self._ended,
            "latency_ms_p50": None if math.isnan(p50) else round(p50, 2),
            "latency_ms_p95": None if math.isnan(p95) else round(p95, 2),
            "source": {**self._plain_source(), **describe_source(self.source)},
        }

    def _plain_source(self) -> dict[str, Any]:
        """What can be said of any source, whatever it says of itself."""
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

    def _take(self, now_ns: int) -> Frame | None:
        """The oldest frame due (ready, or held max_wait_s), skipping those held longer while a
        newer one is due too: a slow registration drops frames instead of lagging. None if no
        frame is due."""
        with self._lock:
            held = self._pending
            late = [now_ns - at >= self.max_wait_ns for _, at in held]
            due = [late[i] or self._is_ready(f) for i, (f, _) in enumerate(held)]
            if not any(due):
                return None
            newest = max(i for i, d in enumerate(due) if d)
            take = next((i for i in range(newest) if due[i] and not late[i]), newest)
            for _ in range(take):
                held.popleft()
                self.stats.dropped += 1
            frame, _ = held.popleft()
            if not self._is_ready(frame):
                self.stats.timed_out += 1
            return frame

    def _is_ready(self, frame: Frame) -> bool:
        """Whether a frame's samples are in (always, without a `ready` test)."""
        return self.ready is None or self.ready(frame)

    def _capture(self, loop: asyncio.AbstractEventLoop, wake: asyncio.Event) -> None:
        """Capture thread: newest frame wins the mailbox."""
        try:
            while not self._stop.is_set():
                frame = self.source.read()
                if frame is None:
                    break
                with self._lock:
                    if len(self._pending) >= PENDING_LIMIT:
                        self._pending.popleft()
                        self.stats.dropped += 1
                    self._pending.append((frame, time.monotonic_ns()))
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
