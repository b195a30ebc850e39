"""A one-way medium with a finite rate: items leave in order, no faster than the line allows.

Each item occupies the line for `cost_bytes / rate_bytes_s` seconds after the previous one has
left, then arrives `delay_s` later (latency and jitter from the fault injector). Arrival times
never go backwards, so jitter delays but does not reorder a byte stream. One task per pipe.
Pipes built on one `Line` take turns on it, as both directions of a half-duplex radio channel.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import time
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")
UART_BITS_PER_BYTE = 10  # start + 8 data + stop


def uart_rate_bytes_s(baud: int) -> float:
    """Bytes per second a UART at `baud` carries with 8N1 framing."""
    return baud / UART_BITS_PER_BYTE


class Line:
    """A medium one item at a time: when it is next free (monotonic seconds)."""

    def __init__(self) -> None:
        self.free_s = 0.0

    def occupy(self, duration_s: float) -> float:
        """Take the medium for `duration_s` as soon as it is free; returns when that ends."""
        self.free_s = max(time.monotonic(), self.free_s) + duration_s
        return self.free_s


class PacedPipe(Generic[T]):
    """Deliver pushed items to `deliver` in order at the modelled rate."""

    def __init__(
        self,
        deliver: Callable[[T], None],
        rate_bytes_s: float | None,
        line: Line | None = None,
    ) -> None:
        self._deliver = deliver
        self._rate: float | None = None
        self.set_rate(rate_bytes_s)
        self._queue: collections.deque[tuple[float, T]] = collections.deque()
        self.line = line or Line()
        self._last_due_s = 0.0
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.items = 0
        self.bytes = 0

    def set_rate(self, rate_bytes_s: float | None) -> None:
        """Change the line rate for items pushed from now on."""
        if rate_bytes_s is not None and rate_bytes_s <= 0:
            raise ValueError(f"rate_bytes_s must be positive, got {rate_bytes_s}")
        self._rate = rate_bytes_s

    def start(self) -> None:
        """Start the delivery task on the running loop."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run())

    async def stop(self) -> None:
        """Stop delivering; anything still on the line is lost, as on a cut cable."""
        task, self._task = self._task, None
        self._queue.clear()
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    def push(self, item: T, cost_bytes: int, delay_s: float = 0.0) -> float:
        """Queue an item that occupies the line for `cost_bytes`; returns when it has left it."""
        left_s = self.line.occupy(cost_bytes / self._rate if self._rate else 0.0)
        due = max(left_s + delay_s, self._last_due_s)
        self._last_due_s = due
        self._queue.append((due, item))
        self.items += 1
        self.bytes += cost_bytes
        self._wake.set()
        return left_s

    @property
    def backlog(self) -> int:
        """Items still on the line."""
        return len(self._queue)

    async def _run(self) -> None:
        """Sleep until the head item is due, then hand it over."""
        while True:
            if not self._queue:
                self._wake.clear()
                await self._wake.wait()
                continue
            due, item = self._queue[0]
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
                continue
            self._queue.popleft()
            self._deliver(item)
