"""A link emulator's own event loop, on a thread of its own: the wire does not wait for the host.

A link emulator paces bytes with its loop's timers and hands them over in its loop's callbacks.
In one process with the daemon (the demo), on the daemon's loop, it moved them only when that
loop got round to it, so a loop busy rendering and registering held the controller's replies
back, more than the probes it answered, and the host's clock sync read the hold as an offset:
over the pty, 1.5 ms with the loop blocked 5 ms in every 10, 0.4 ms with the emulator on a loop
of its own (2026-12-03). A cable has no such wait.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Coroutine
from typing import Any, TypeVar

T = TypeVar("T")
JOIN_TIMEOUT_S = 5.0


class WireLoop:
    """An event loop running in a daemon thread: a link emulator's, or the test suite's browser."""

    def __init__(self, name: str = "hil-wire") -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread (once)."""
        self._thread.start()

    async def run(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run a coroutine on the wire's loop and await its result from another loop."""
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(coro, self.loop))

    def stop(self) -> None:
        """Stop the loop, join the thread and close the loop (what was scheduled is dropped)."""
        if self._thread.is_alive():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(JOIN_TIMEOUT_S)
        if not self._thread.is_alive() and not self.loop.is_closed():
            self.loop.close()
