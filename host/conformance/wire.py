"""The suite's own client: raw frames over any host transport, with explicit seq and flags.

It is deliberately not the host's Session: a conformance check must send what a conforming host
never would (gaps, stale seqs, repeats with other content, unknown ids, damaged frames) and see
every frame the controller sends, in order, with its arrival time.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from host.transport.base import Transport
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, Flag, FrameDecoder, Packet, encode_frame
from protocol.messages import ClockSyncReply, Heartbeat, Hello, Identify, Status

SEQ_MOD = 1 << 16
HEARTBEAT_INTERVAL_S = 0.04  # inside the shortest watchdog the suite sets (100 ms), light on radio
REPLY_TIMEOUT_S = 0.4
REPLY_TRIES = 4
MessageT = TypeVar("MessageT")


class ConformanceError(AssertionError):
    """A controller broke a rule; the message says what was expected and what came."""


class NotApplicable(Exception):  # noqa: N818  (a verdict, not an error)
    """The check tests an optional feature the controller does not offer: reported as skipped."""


@dataclass(frozen=True)
class Received:
    """One controller frame and when it arrived (monotonic seconds)."""

    packet: Packet
    at_s: float

    @property
    def message(self) -> Any:
        """The decoded message."""
        return self.packet.message


class WireClient:
    """Frames to and from one controller; the command seq is in the caller's hands."""

    def __init__(self, transport: Transport) -> None:
        self.transport = transport
        self.decoder = FrameDecoder()
        self.received: list[Received] = []
        self.seq = random.randrange(SEQ_MOD)  # the next command seq
        self.session_id = random.randrange(1 << 32)
        self.identity: Identify | None = None
        self.heartbeats = True  # False: go silent (watchdog checks)
        self._arrived = asyncio.Event()
        self._sent_at: dict[int, int] = {}  # seq → frames received when it was last sent
        self._task: asyncio.Task[None] | None = None

    async def open(self) -> None:
        """Open the transport, flush the controller's partial frame, start heartbeats."""
        self.transport.set_receiver(self._on_bytes, None)
        await self.transport.open()
        self.transport.send(b"\x00")
        self._task = asyncio.create_task(self._heartbeat_loop(), name="conformance-heartbeat")

    async def close(self) -> None:
        """Stop heartbeats and close the transport."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self.transport.close()

    # ---- sending ----------------------------------------------------------------------

    def take_seq(self) -> int:
        """The next command seq, spent."""
        seq = self.seq
        self.seq = (seq + 1) % SEQ_MOD
        return seq

    def send(self, msg: object, seq: int, flags: int = Flag.ACK_REQUESTED) -> None:
        """One frame with the given seq and flags."""
        self._sent_at[seq] = len(self.received)
        self.transport.send(encode_frame(msg, seq, flags))

    def send_raw(self, wire: bytes, seq: int | None = None) -> None:
        """Bytes as they are (damaged frames, other versions); `seq` if they carry one."""
        if seq is not None:
            self._sent_at[seq] = len(self.received)
        self.transport.send(wire)

    async def request(
        self, msg: object, seq: int | None = None, timeout_s: float = REPLY_TIMEOUT_S
    ) -> Any:
        """An acked command and its reply; retransmitted with the same seq on silence."""
        seq = self.take_seq() if seq is None else seq
        start = len(self.received)
        for attempt in range(REPLY_TRIES):
            flags = Flag.ACK_REQUESTED | (Flag.RETRANSMIT if attempt else Flag.NONE)
            self.send(msg, seq, flags)
            reply = await self.wait_reply(seq, timeout_s, start)
            if reply is not None:
                return reply
        name = type(msg).__name__
        raise ConformanceError(f"no reply to {name} seq {seq} after {REPLY_TRIES} tries")

    async def hello(self, capabilities: int = 0) -> Identify:
        """HELLO at the next seq (it starts the command sequence); the IDENTIFY."""
        msg = Hello(PROTOCOL_VERSION, SCHEMA_HASH, capabilities, self.session_id)
        ident = await self.request(msg)
        if not isinstance(ident, Identify):
            raise ConformanceError(f"HELLO answered {ident!r}, expected IDENTIFY")
        self.identity = ident
        return ident

    # ---- receiving --------------------------------------------------------------------

    def mark(self) -> int:
        """A position in the received frames, for 'what came after this'."""
        return len(self.received)

    def since(self, mark: int, cls: type[MessageT]) -> list[MessageT]:
        """Messages of one type received after `mark`."""
        return [r.message for r in self.received[mark:] if isinstance(r.message, cls)]

    async def wait_reply(self, seq: int, timeout_s: float, start: int | None = None) -> Any | None:
        """The first reply naming seq received after `start` (default: its last send), or None."""
        start = self._sent_at.get(seq, 0) if start is None else start
        found = await self.wait_for(
            lambda r: _answers(r.message, seq), timeout_s, start, raise_on_timeout=False
        )
        return None if found is None else found.message

    async def replies_to(self, seq: int, within_s: float, start: int = 0) -> list[Any]:
        """Every reply naming seq that arrives within the time (for 'no reply' checks)."""
        await asyncio.sleep(within_s)
        return [r.message for r in self.received[start:] if _answers(r.message, seq)]

    async def wait_status(
        self, accept: Callable[[Status], bool], timeout_s: float, start: int, what: str
    ) -> Status:
        """The first STATUS after `start` that `accept`s, or ConformanceError naming `what`."""
        found = await self.wait_for(
            lambda r: isinstance(r.message, Status) and accept(r.message), timeout_s, start
        )
        assert found is not None
        return found.message  # type: ignore[no-any-return]

    async def wait_for(
        self,
        accept: Callable[[Received], bool],
        timeout_s: float,
        start: int = 0,
        raise_on_timeout: bool = True,
    ) -> Received | None:
        """The first received frame after `start` that `accept`s."""
        deadline = time.monotonic() + timeout_s
        index = start
        while True:
            while index < len(self.received):
                item = self.received[index]
                index += 1
                if accept(item):
                    return item
            left = deadline - time.monotonic()
            if left <= 0:
                if raise_on_timeout:
                    raise ConformanceError(f"nothing acceptable within {timeout_s:.1f} s")
                return None
            self._arrived.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._arrived.wait(), left)

    def _on_bytes(self, data: bytes) -> None:
        """Transport receiver: keep every good frame with its arrival time."""
        now = time.monotonic()
        for packet in self.decoder.feed(data):
            self.received.append(Received(packet, now))
        self._arrived.set()

    async def _heartbeat_loop(self) -> None:
        """Feed the controller's watchdog unless told to be silent; no seq is spent."""
        while True:
            await asyncio.sleep(HEARTBEAT_INTERVAL_S)
            if self.heartbeats:
                uptime_ms = int(time.monotonic() * 1000) & 0xFFFF_FFFF
                self.send(Heartbeat(uptime_ms), self.seq, Flag.NONE)


def _answers(msg: object, seq: int) -> bool:
    """Whether msg is a command reply naming seq (clock replies are not command replies)."""
    return getattr(msg, "req_seq", None) == seq and not isinstance(msg, ClockSyncReply)
