"""An in-process transport for tests and the lockstep simulator, with seeded link impairments.

`MemoryTransport._write` hands each frame to a peer callback (the other end: a fake controller,
the firmware mirror's byte input, or another MemoryTransport), through a `Channel` that can lose,
duplicate, delay and reorder frames, drawing from its own seeded RNG so a run repeats exactly.
The peer answers through `inject`, which goes through the reverse channel to the receiver.
"""

from __future__ import annotations

import asyncio
import random
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from host.transport.base import Transport, TransportError, TransportState

Sink = Callable[[bytes], None]
FIFO_TOKEN = -1  # key of the one timer of an order-keeping channel


@dataclass(frozen=True)
class Impairment:
    """What a channel does to each frame; all probabilities per frame."""

    loss: float = 0.0
    duplicate: float = 0.0
    delay_s: float = 0.0
    jitter_s: float = 0.0  # uniform extra delay in [0, jitter_s]
    keep_order: bool = True  # a serial line never reorders; a radio mesh may

    def __post_init__(self) -> None:
        if not (0.0 <= self.loss <= 1.0 and 0.0 <= self.duplicate <= 1.0):
            raise ValueError("loss and duplicate are probabilities in [0, 1]")
        if self.delay_s < 0.0 or self.jitter_s < 0.0:
            raise ValueError("delay_s and jitter_s must be >= 0")


@dataclass
class ChannelStats:
    """What a channel did, to compare with what the session counted."""

    sent: int = 0
    lost: int = 0
    duplicated: int = 0
    delivered: int = 0
    dropped_closed: int = 0  # frames in flight when the channel closed


@dataclass
class Channel:
    """One direction of an impaired link: frames in, frames out to `sink` later."""

    sink: Sink
    impairment: Impairment = field(default_factory=Impairment)
    seed: int = 0
    stats: ChannelStats = field(default_factory=ChannelStats)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)
        self._pending: dict[int, asyncio.TimerHandle | asyncio.Handle] = {}
        self._fifo: deque[tuple[float, bytes]] = deque()
        self._next_token = 0

    def send(self, frame: bytes) -> None:
        """Pass one frame through the impairments."""
        self.stats.sent += 1
        imp = self.impairment
        if imp.loss and self._rng.random() < imp.loss:
            self.stats.lost += 1
            return
        copies = 2 if imp.duplicate and self._rng.random() < imp.duplicate else 1
        self.stats.duplicated += copies - 1
        for _ in range(copies):
            self._schedule(frame)

    def close(self) -> None:
        """Cancel every frame still in flight."""
        for handle in self._pending.values():
            handle.cancel()
        self.stats.dropped_closed += (
            len(self._fifo) + len(self._pending) - (FIFO_TOKEN in self._pending)
        )
        self._pending.clear()
        self._fifo.clear()

    def _schedule(self, frame: bytes) -> None:
        """Deliver after the drawn delay: through one FIFO if the link keeps order."""
        loop = asyncio.get_running_loop()
        imp = self.impairment
        delay = imp.delay_s + (self._rng.uniform(0.0, imp.jitter_s) if imp.jitter_s else 0.0)
        due = loop.time() + delay
        if not imp.keep_order:
            token = self._next_token
            self._next_token += 1
            self._pending[token] = loop.call_at(due, self._deliver, token, frame)
            return
        # Timers with equal deadlines may fire in any order: one queue, one timer at a time.
        self._fifo.append((max(due, self._fifo[-1][0] if self._fifo else due), frame))
        if FIFO_TOKEN not in self._pending:
            self._arm_fifo(loop)

    def _arm_fifo(self, loop: asyncio.AbstractEventLoop) -> None:
        """One timer for the queue's head; a frame already due goes on the next loop pass."""
        due = self._fifo[0][0]
        if due <= loop.time():
            self._pending[FIFO_TOKEN] = loop.call_soon(self._drain_fifo)
        else:
            self._pending[FIFO_TOKEN] = loop.call_at(due, self._drain_fifo)

    def _drain_fifo(self) -> None:
        """Deliver every queued frame that is due, in order, then re-arm for the next."""
        del self._pending[FIFO_TOKEN]
        loop = asyncio.get_running_loop()
        while self._fifo and self._fifo[0][0] <= loop.time():
            _, frame = self._fifo.popleft()
            self.stats.delivered += 1
            self.sink(frame)
        if self._fifo and FIFO_TOKEN not in self._pending:
            self._arm_fifo(loop)

    def _deliver(self, token: int, frame: bytes) -> None:
        """Timer callback: forget the handle, hand the frame over."""
        del self._pending[token]
        self.stats.delivered += 1
        self.sink(frame)


class MemoryTransport(Transport):
    """Transport whose other end is a callback in the same process."""

    scheme = "memory"

    def __init__(
        self,
        peer: Sink | None = None,
        *,
        tx: Impairment | None = None,
        rx: Impairment | None = None,
        seed: int = 0,
        name: str = "memory",
    ) -> None:
        super().__init__()
        self.name = name
        self.available = True  # False makes open() fail, as an unplugged device would
        self._peer: Sink = peer if peer is not None else _discard
        self.tx = Channel(self._to_peer, tx or Impairment(), seed)
        self.rx = Channel(self._from_peer, rx or Impairment(), seed + 1)

    def attach_peer(self, peer: Sink) -> None:
        """Set where sent frames go."""
        self._peer = peer

    def inject(self, data: bytes) -> None:
        """The peer sends bytes towards the receiver (through the rx impairments)."""
        self.rx.send(data)

    def disconnect(self, exc: Exception | None = None) -> None:
        """Simulate the device vanishing: in-flight frames die and the session is told."""
        self.tx.close()
        self.rx.close()
        self._lost(exc or TransportError(f"{self.describe()} vanished"))

    def describe(self) -> str:
        """Name for messages."""
        return f"memory link {self.name}"

    async def _open(self) -> None:
        if not self.available:
            raise TransportError(f"{self.describe()} is not available")

    def _write(self, frame: bytes) -> None:
        self.tx.send(frame)

    async def _close(self) -> None:
        self.tx.close()
        self.rx.close()

    def _to_peer(self, frame: bytes) -> None:
        """Frames reach the peer only while the link is open."""
        if self.state is TransportState.OPEN:
            self._peer(frame)

    def _from_peer(self, data: bytes) -> None:
        """Bytes reach the receiver only while the link is open."""
        if self.state is TransportState.OPEN:
            self._deliver(data)


def memory_pair(
    a_to_b: Impairment | None = None, b_to_a: Impairment | None = None, seed: int = 0
) -> tuple[MemoryTransport, MemoryTransport]:
    """Two transports wired back to back: what one sends, the other receives."""
    a = MemoryTransport(tx=a_to_b, seed=seed, name="a")
    b = MemoryTransport(tx=b_to_a, seed=seed + 2, name="b")
    a.attach_peer(b._from_peer)
    b.attach_peer(a._from_peer)
    return a, b


def _discard(_frame: bytes) -> None:
    """Peer of a transport nobody listens to."""
