"""The transport contract: move whole wire frames between the host and the controller.

A transport knows nothing of messages. `send` takes one encoded wire frame (COBS bytes and the
trailing 0x00 delimiter, as `protocol.encode_frame` returns); received bytes go to the receiver
callback as a byte stream that `protocol.FrameDecoder.feed` accepts (datagram transports hand
over whole frames, serial ones any chunk). Subclasses fill the `_open`, `_write` and `_close`
hooks; the base class owns the public methods, the state and the statistics.
"""

from __future__ import annotations

import abc
import enum
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

Receiver = Callable[[bytes], None]
LostHandler = Callable[[Exception | None], None]
# Sees every received chunk and every sent frame: ("rx" | "tx", host monotonic ns, bytes).
ByteTap = Callable[[str, int, bytes], None]

log = logging.getLogger(__name__)


class TransportError(ConnectionError):
    """The link cannot be opened or used; the message says which device and why."""


class FrameTooLargeError(TransportError):
    """A frame longer than the backend can carry was refused; the link stays up."""


class TransportState(enum.Enum):
    """Where a transport is in its life."""

    CLOSED = "closed"
    OPENING = "opening"
    OPEN = "open"
    LOST = "lost"


@dataclass
class TransportStats:
    """Counters every transport keeps; backends add their own under `extra`."""

    frames_out: int = 0
    bytes_out: int = 0
    chunks_in: int = 0
    bytes_in: int = 0
    write_errors: int = 0
    opens: int = 0
    losses: int = 0
    extra: dict[str, int] = field(default_factory=dict)

    def bump(self, key: str, n: int = 1) -> None:
        """Increment a backend-specific counter."""
        self.extra[key] = self.extra.get(key, 0) + n


class Transport(abc.ABC):
    """Base class of every link backend (serial, XBee, CAN)."""

    scheme: ClassVar[str]  # backend name used in config and BACKENDS
    max_frame_bytes: ClassVar[int | None] = None  # largest frame the medium carries, if limited

    def __init__(self) -> None:
        self.stats = TransportStats()
        self.state = TransportState.CLOSED
        self._receiver: Receiver | None = None
        self._on_lost: LostHandler | None = None
        self._tap: ByteTap | None = None
        # Host monotonic ns of the chunk being delivered and of the last frame written: the
        # session stamps its clock probes with these, the very stamps the tap records.
        self.rx_time_ns = 0
        self.tx_time_ns = 0

    def set_receiver(self, receiver: Receiver, on_lost: LostHandler | None = None) -> None:
        """Route received bytes (and the news of a lost link) to the session."""
        self._receiver = receiver
        self._on_lost = on_lost

    def set_tap(self, tap: ByteTap | None) -> None:
        """Hand every received chunk and sent frame, with its host time, to `tap` (recording)."""
        self._tap = tap

    async def open(self) -> None:
        """Open the link; TransportError with the reason if the device is not there."""
        self.state = TransportState.OPENING
        try:
            await self._open()
        except TransportError:
            self.state = TransportState.CLOSED
            raise
        except (OSError, ValueError) as exc:
            self.state = TransportState.CLOSED
            raise TransportError(f"{self.describe()}: {exc}") from exc
        self.state = TransportState.OPEN
        self.stats.opens += 1

    async def close(self) -> None:
        """Close the link; safe to call twice or on a lost link."""
        if self.state is not TransportState.CLOSED:
            self.state = TransportState.CLOSED
            await self._close()

    def send(self, frame: bytes) -> None:
        """Queue one wire frame for sending without blocking; TransportError when not open."""
        if self.state is not TransportState.OPEN:
            raise TransportError(f"{self.describe()} is {self.state.value}")
        limit = self.max_frame_bytes
        if limit is not None and len(frame) > limit:
            self.stats.bump("oversize_refused")
            raise FrameTooLargeError(f"{self.describe()}: frame of {len(frame)} bytes > {limit}")
        t_ns = time.monotonic_ns()  # taken before the write, as near the caller's stamp as can be
        try:
            self._write(frame)
        except (OSError, ValueError) as exc:
            self.stats.write_errors += 1
            self._lost(exc)
            raise TransportError(f"{self.describe()}: {exc}") from exc
        self.stats.frames_out += 1
        self.stats.bytes_out += len(frame)
        self.tx_time_ns = t_ns
        if self._tap is not None:
            self._tapped("tx", t_ns, frame)

    def resync(self) -> None:
        """Forget partial receive state when a session (re)starts; backends with any override.

        A controller that rebooted restarts its own framing state (CAN's segment counter), so a
        half-received frame from before can never complete and must not block the new ones.
        Stream backends keep no such state (the session's decoder does): nothing to do.
        """
        return

    @abc.abstractmethod
    def describe(self) -> str:
        """Human-readable name of the link, e.g. 'serial /dev/ttyUSB0 @115200'."""

    @abc.abstractmethod
    async def _open(self) -> None:
        """Backend hook: open the device and start delivering bytes to `_deliver`."""

    @abc.abstractmethod
    def _write(self, frame: bytes) -> None:
        """Backend hook: hand one wire frame to the device without blocking."""

    @abc.abstractmethod
    async def _close(self) -> None:
        """Backend hook: release the device."""

    def _deliver(self, data: bytes) -> None:
        """Backends call this with received bytes."""
        self.stats.chunks_in += 1
        self.stats.bytes_in += len(data)
        self.rx_time_ns = time.monotonic_ns()
        if self._tap is not None:
            self._tapped("rx", self.rx_time_ns, data)
        if self._receiver is not None:
            self._receiver(data)

    def _tapped(self, direction: str, t_ns: int, data: bytes) -> None:
        """Give the tap its bytes; a failing tap is counted, never the link's problem."""
        assert self._tap is not None
        try:
            self._tap(direction, t_ns, bytes(data))
        except Exception:
            self.stats.bump("tap_errors")
            if self.stats.extra["tap_errors"] == 1:
                log.exception("the link byte tap failed (counted in tap_errors from now on)")

    def _lost(self, exc: Exception | None) -> None:
        """Backends call this when the device went away (unplugged, bus off, radio gone)."""
        if self.state is TransportState.OPEN:
            self.state = TransportState.LOST
            self.stats.losses += 1
            if self._on_lost is not None:
                self._on_lost(exc)
