"""From the frame loop to the viewers: newest-only at every stage, encoding off the event loop.

The frame loop (or, without a camera, the pose publisher) calls `submit` on the event loop; that
only swaps a reference, so it never waits. One encoder task takes the newest submission, draws
and encodes it in a worker thread, and offers the JPEG to every viewer's one-frame slot; a
viewer that has not taken the previous one loses it (counted), so a slow or stalled client holds
at most one frame and never slows anything else. Nothing is drawn while nobody watches.
Each viewer says whether it wants the ghost (the encoder-only registration) drawn; a view is
drawn once per choice its viewers have made, so only a mix of choices costs a second encode.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from host.station.render import EncodedView, ViewInput, ViewRenderer

log = logging.getLogger(__name__)

WINDOW = 256  # recent frames kept for the rates and percentiles
FRESH_NS = 500_000_000  # a frame this recent is a new viewer's first


class ViewerSlot:
    """One viewer's mailbox: the newest encoded frame it has not taken yet."""

    def __init__(self, ghost: bool = True) -> None:
        self.ghost = ghost  # draw the encoder-only registration in this viewer's frames
        self.frame: EncodedView | None = None
        self.offered = 0
        self.dropped = 0  # frames replaced before this viewer took them
        self.on_offer: Callable[[], None] | None = None  # a writer to wake, if not take()
        self._ready = asyncio.Event()

    def offer(self, frame: EncodedView) -> None:
        """Put the newest frame in; an untaken older one is dropped."""
        if self.frame is not None:
            self.dropped += 1
        self.frame = frame
        self.offered += 1
        self._ready.set()
        if self.on_offer is not None:
            self.on_offer()

    async def take(self) -> EncodedView:
        """Wait for a frame and take it."""
        while self.frame is None:
            self._ready.clear()
            await self._ready.wait()
        frame, self.frame = self.frame, None
        return frame


@dataclass
class HubStats:
    """What the hub did, for the status panel and the benchmark."""

    submitted: int = 0
    encoded: int = 0
    dropped: int = 0  # submissions replaced before the encoder took them
    failed: int = 0
    cpu_ms: deque[float] = field(default_factory=lambda: deque(maxlen=WINDOW))
    encoded_ns: deque[int] = field(default_factory=lambda: deque(maxlen=WINDOW))
    ready_ms: deque[float] = field(default_factory=lambda: deque(maxlen=WINDOW))  # exposure→JPEG

    def fps(self) -> float:
        """Frames encoded per second, recently."""
        times = self.encoded_ns
        if len(times) < 2 or times[-1] == times[0]:
            return 0.0
        return (len(times) - 1) / ((times[-1] - times[0]) / 1e9)

    def cpu_ms_mean(self) -> float:
        """Mean CPU time per frame to draw and encode."""
        return sum(self.cpu_ms) / len(self.cpu_ms) if self.cpu_ms else 0.0


class FrameHub:
    """Newest view in, newest JPEG out to each viewer."""

    def __init__(self, renderer: ViewRenderer, ghost: bool = True) -> None:
        self.renderer = renderer
        self.ghost = ghost  # the default of a new viewer (`[ui] ghost`)
        self.stats = HubStats()
        self.latest: EncodedView | None = None
        self._latest_by_ghost: dict[bool, EncodedView] = {}
        self._viewers: set[ViewerSlot] = set()
        self._pending: ViewInput | None = None
        self._wake = asyncio.Event()
        self._executor = concurrent.futures.ThreadPoolExecutor(1, "station-encode")
        self._task: asyncio.Task[None] | None = None

    @property
    def viewer_count(self) -> int:
        """Viewers connected now (pages and MJPEG streams)."""
        return len(self._viewers)

    def start(self) -> None:
        """Start the encoder task on the running loop."""
        self._task = asyncio.get_running_loop().create_task(self._run(), name="station-encode")

    async def close(self) -> None:
        """Stop the encoder and its thread."""
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        self._executor.shutdown(wait=False, cancel_futures=True)

    def submit(self, view: ViewInput) -> None:
        """Hand over the newest view (event loop only; never waits, never raises)."""
        if not self._viewers:
            return
        if self._pending is not None:
            self.stats.dropped += 1
        self._pending = view
        self.stats.submitted += 1
        self._wake.set()

    def attach(self, ghost: bool | None = None) -> ViewerSlot:
        """A new viewer; a recent frame is its first at once (nothing is drawn while unwatched,
        so an older one would show the past: the next view is drawn for it instead)."""
        slot = ViewerSlot(self.ghost if ghost is None else ghost)
        self._viewers.add(slot)
        first = self._latest_by_ghost.get(slot.ghost, self.latest)
        if first is not None and time.monotonic_ns() - first.encoded_ns < FRESH_NS:
            slot.offer(first)
        return slot

    def detach(self, slot: ViewerSlot) -> None:
        """A viewer left."""
        self._viewers.discard(slot)

    async def _run(self) -> None:
        """Encode the newest view whenever there is one, once per ghost choice watching."""
        loop = asyncio.get_running_loop()
        while True:
            await self._wake.wait()
            self._wake.clear()
            view, self._pending = self._pending, None
            if view is None:
                continue
            frames = []
            for ghost in sorted({slot.ghost for slot in self._viewers}, reverse=True):
                try:
                    frame = await loop.run_in_executor(
                        self._executor, self.renderer.render, view, ghost
                    )
                except Exception:
                    self.stats.failed += 1
                    if self.stats.failed <= 3:
                        log.exception("station frame %d could not be drawn", view.index)
                    break
                frames.append((ghost, frame))
            else:
                if frames:
                    self._deliver(frames)

    def _deliver(self, frames: list[tuple[bool, EncodedView]]) -> None:
        """Offer a fresh JPEG to every viewer, the one drawn for its ghost choice."""
        first = frames[0][1]
        self.latest = first
        self.stats.encoded += 1
        self.stats.cpu_ms.append(sum(f.cpu_ms for _, f in frames))
        self.stats.encoded_ns.append(time.monotonic_ns())
        self.stats.ready_ms.append((first.encoded_ns - first.exposure_ns) / 1e6)
        by_ghost = dict(frames)
        self._latest_by_ghost.update(by_ghost)
        for slot in self._viewers:
            frame = by_ghost.get(slot.ghost)
            if frame is not None:  # None: it chose while this view was drawn; the next is its
                slot.offer(frame)
