"""The firmware's side of the link: bounded RX framing, the TX queue and the reply cache.

Unlike `protocol.FrameDecoder`, the receive path keeps the header of a frame whose id or
payload it cannot decode, because the controller must still NAK it by seq (UNKNOWN_MESSAGE,
BAD_PAYLOAD). Buffers are fixed-size, as in the C: a frame longer than the largest legal one
is discarded up to its delimiter and counted; the TX queue sends replies before telemetry, and
when full drops telemetry (counted) while replies keep a reserve of slots.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass

from firmware.config import (
    MAX_FRAME_BYTES,
    REPLY_CACHE_SIZE,
    TX_QUEUE_FRAMES,
    TX_REPLY_RESERVE_FRAMES,
)
from protocol import PROTOCOL_VERSION, encode_frame
from protocol.cobs import CobsError
from protocol.cobs import decode as cobs_decode
from protocol.compat import HANDSHAKE_IDS, LEGACY_VERSION, encode_v1, legacy_frame_ok
from protocol.crc import FRAME_RESIDUE, crc16
from protocol.schema import CRC_SIZE, HEADER_FORMAT, HEADER_SIZE, QUIET_HOLD_US

_HEADER = struct.Struct(HEADER_FORMAT)
_U32 = 0xFFFF_FFFF
CATCH_UP = 4  # a held frame's delay shrinks 1 µs every CATCH_UP µs (TxQueue)
_DELIM = b"\x00"
_MIN_RAW = HEADER_SIZE + CRC_SIZE
_HELLO_ID = min(HANDSHAKE_IDS)  # 0x01; IDENTIFY (0x80) never comes from the host


@dataclass
class LinkCounters:
    """Receive and transmit statistics of the controller's link."""

    frames_in: int = 0
    bad_cobs: int = 0
    bad_crc: int = 0
    bad_length: int = 0
    bad_version: int = 0
    oversize: int = 0
    frames_out: int = 0
    tx_dropped: int = 0
    duplicates: int = 0  # repeats answered from the reply memory
    held: int = 0  # commands that arrived ahead of a gap and waited for it
    stale: int = 0  # NAK STALE_SEQ: behind the sequence and not a remembered repeat
    unacked_commands: int = 0  # acked-only commands sent without ACK_REQUESTED, ignored


class RxFramer:
    """Splits the byte stream into checked frames: (seq, flags, msg_id, raw frame)."""

    __slots__ = ("_buf", "_discarding", "counters")

    def __init__(self, counters: LinkCounters) -> None:
        self.counters = counters
        self._buf = bytearray()
        self._discarding = False

    def reset(self) -> None:
        """Forget a partial frame (reset, resync)."""
        self._buf.clear()
        self._discarding = False

    def feed(self, data: bytes) -> list[tuple[int, int, int, bytes, int]]:
        """Consume received bytes; the frames that passed COBS, length, CRC and version.

        Each is (seq, flags, msg_id, raw without CRC, version); a version other than ours is
        only ever a HELLO, kept so that it can be answered (PROTOCOL §7).
        """
        if _DELIM not in data:
            self._append(data)
            return []
        parts = data.split(_DELIM)
        out: list[tuple[int, int, int, bytes, int]] = []
        for i, part in enumerate(parts):
            self._append(part)
            if i == len(parts) - 1:
                break
            if self._discarding:
                self._discarding = False  # the delimiter ends an oversize frame
            elif self._buf:
                frame = self._check(bytes(self._buf))
                if frame is not None:
                    out.append(frame)
            self._buf.clear()
        return out

    def _append(self, data: bytes) -> None:
        """Add bytes to the partial frame, discarding it once it outgrows the largest frame."""
        if self._discarding:
            return
        self._buf += data
        if len(self._buf) > MAX_FRAME_BYTES - 1:
            self.counters.oversize += 1
            self._discarding = True
            self._buf.clear()

    def _check(self, enc: bytes) -> tuple[int, int, int, bytes, int] | None:
        """One delimited frame → header and raw bytes, or None with the reason counted."""
        c = self.counters
        try:
            raw = cobs_decode(enc)
        except CobsError:
            c.bad_cobs += 1
            return None
        if len(raw) < _MIN_RAW:
            c.bad_length += 1
            return None
        legacy = legacy_frame_ok(raw)
        if crc16(raw) != FRAME_RESIDUE and not legacy:
            c.bad_crc += 1
            return None
        version, flags, seq, msg_id = _HEADER.unpack_from(raw)
        if version != PROTOCOL_VERSION and (
            msg_id != _HELLO_ID or (version == LEGACY_VERSION and not legacy)
        ):
            c.bad_version += 1
            return None
        c.frames_in += 1
        return seq, flags, msg_id, raw[: len(raw) - CRC_SIZE], version


class TxQueue:
    """Outgoing frames, bounded in count, replies ahead of telemetry; each frame gets a u16 seq.

    Two FIFOs, as in the C: replies (ACK/NAK, the answers to HELLO, PARAM_GET and CLOCK_SYNC,
    event STATUS) and telemetry. `drain` takes replies first, so a reply waits at most behind
    the one frame already being written, never behind queued batches (PROTOCOL.md §14,
    R-STREAM-1). A frame's seq is given when it is framed for the wire, so the host still sees
    the seqs in order. When the link carries less than the streams produce, frames wait here;
    once the queue is full the oldest waiting telemetry is dropped and its seq spent (the host
    counts the loss), never a reply: replies always find a slot.

    Telemetry held back (a quiet clock probe's hold, PROTOCOL.md §8) leaves with the spacing it
    was queued with, shifted by the hold, instead of in one burst: a radio module's serial
    buffer (202 bytes on an XBee) takes a hold's worth of frames only as fast as the air does.
    Each telemetry frame is stamped with `now_us` (the tick's time, set by the firmware) when
    queued and leaves no sooner than the delay after it; the delay shrinks by one µs every
    CATCH_UP µs (frames then leave 1 / (1 − 1 / CATCH_UP) times as fast as they were made, so
    a 40 ms hold is made up within 160 ms) and is dropped once the telemetry queue is empty.
    """

    __slots__ = (
        "_delay_at_us",
        "_delay_us",
        "_pending",
        "_replies",
        "_telemetry",
        "counters",
        "now_us",
        "seq",
    )

    def __init__(self, counters: LinkCounters) -> None:
        self.counters = counters
        self._replies: deque[tuple[object, int, bool]] = deque()  # (message, flags, legacy)
        self._telemetry: deque[tuple[object, int, bool, int]] = deque()  # ... queued at µs
        self._pending: bytes | None = None  # framed (its seq given) but not yet taken by the link
        self.seq = 0
        self.now_us = 0
        self._delay_us = 0  # the telemetry delay when last set, at _delay_at_us
        self._delay_at_us = 0

    def __len__(self) -> int:
        return len(self._replies) + len(self._telemetry) + (self._pending is not None)

    def reset(self) -> None:
        """Empty the queue and restart the seq (controller reset)."""
        self._replies.clear()
        self._telemetry.clear()
        self._pending = None
        self.seq = 0
        self._delay_us = 0

    def delay_telemetry(self, held_us: int) -> None:
        """Telemetry was held for `held_us`: what waits leaves that much later than queued.

        A hold while frames from an earlier one still wait adds to what is left of its delay,
        up to two holds' bound, so a sample's age grows by at most that.
        """
        if self._telemetry:
            self._delay_us = min(self.delay_us() + held_us, 2 * QUIET_HOLD_US)
            self._delay_at_us = self.now_us

    def delay_us(self) -> int:
        """The telemetry delay now: 0 when frames leave as they are queued."""
        if not self._delay_us:
            return 0
        caught_up = ((self.now_us - self._delay_at_us) & _U32) // CATCH_UP
        return max(0, self._delay_us - caught_up)

    def send(self, msg: object, reply: bool = False, flags: int = 0, legacy: bool = False) -> bool:
        """Queue a message; False if it was telemetry dropped for room.

        `legacy` frames an IDENTIFY as version 1, for a version-1 host's HELLO.
        """
        limit = TX_QUEUE_FRAMES if reply else TX_QUEUE_FRAMES - TX_REPLY_RESERVE_FRAMES
        if len(self) >= limit and not self._drop_oldest_telemetry() and not reply:
            self._spend_dropped()  # nothing older to drop: this one goes
            return False
        if reply:
            self._replies.append((msg, flags, legacy))
        else:
            self._telemetry.append((msg, flags, legacy, self.now_us))
        return True

    def drain(self, room: int, telemetry: bool = True) -> bytes:
        """The queued frames that fit in `room` bytes, replies first, as one byte string.

        `telemetry` False writes replies only (a quiet clock probe's hold, PROTOCOL.md §8);
        a frame already framed for the wire still goes first.
        """
        out: list[bytes] = []
        used = 0
        while True:
            if self._pending is None:
                if self._replies:
                    self._pending = self._frame(*self._replies.popleft())
                elif telemetry and self._telemetry_due():
                    msg, flags, legacy, _ = self._telemetry.popleft()
                    self._pending = self._frame(msg, flags, legacy)
                else:
                    break
            if used + len(self._pending) > room:
                break  # it goes first next time: its seq is given
            out.append(self._pending)
            used += len(self._pending)
            self._pending = None
        self.counters.frames_out += len(out)
        return b"".join(out)

    def _telemetry_due(self) -> bool:
        """Whether the oldest telemetry frame may leave now (its delay since queued is over)."""
        if not self._telemetry:
            self._delay_us = 0  # caught up: frames leave as they are queued again
            return False
        delay = self.delay_us()
        return not delay or (self.now_us - self._telemetry[0][3]) & _U32 >= delay

    def _frame(self, msg: object, flags: int, legacy: bool) -> bytes:
        """The wire bytes of a message, with the next seq of this direction."""
        seq = self.seq
        self.seq = (seq + 1) & 0xFFFF
        return encode_v1(msg, seq, flags) if legacy else encode_frame(msg, seq, flags)

    def _spend_dropped(self) -> None:
        """A telemetry frame is dropped: count it and spend its seq, so the host sees a gap."""
        self.counters.tx_dropped += 1
        self.seq = (self.seq + 1) & 0xFFFF

    def _drop_oldest_telemetry(self) -> bool:
        """Remove the oldest queued telemetry frame; False if every queued frame is a reply."""
        if not self._telemetry:
            return False
        self._telemetry.popleft()
        self._spend_dropped()
        return True


class ReplyCache:
    """The replies sent to the last few executed commands, keyed by seq (PROTOCOL.md §6).

    Each entry also keeps the command's id and payload, so a frame that reuses a remembered
    seq with other content is recognised (and refused) instead of being taken for a repeat.
    """

    __slots__ = ("_entries",)

    def __init__(self) -> None:
        self._entries: dict[int, tuple[bytes, object]] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        """Forget all replies (controller reset, HELLO)."""
        self._entries.clear()

    def lookup(self, seq: int) -> tuple[bytes, object] | None:
        """(command body, reply) remembered for this seq, or None."""
        return self._entries.get(seq)

    def store(self, seq: int, body: bytes, reply: object) -> None:
        """Remember the reply to a command, evicting the oldest beyond REPLY_CACHE_SIZE."""
        entries = self._entries
        entries.pop(seq, None)
        entries[seq] = (body, reply)
        if len(entries) > REPLY_CACHE_SIZE:
            del entries[next(iter(entries))]


class HoldBuffer:
    """Acked commands that arrived ahead of a gap in the command sequence, by seq (bounded)."""

    __slots__ = ("_frames",)

    def __init__(self) -> None:
        self._frames: dict[int, tuple[int, int, bytes]] = {}

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, seq: int) -> bool:
        return seq in self._frames

    def clear(self) -> None:
        """Drop every held frame (reset, HELLO)."""
        self._frames.clear()

    def put(self, seq: int, flags: int, msg_id: int, raw: bytes) -> None:
        """Hold one frame; a repeat of a held seq keeps the first copy."""
        self._frames.setdefault(seq, (flags, msg_id, raw))

    def pop(self, seq: int) -> tuple[int, int, bytes] | None:
        """The frame held for this seq, removed, or None."""
        return self._frames.pop(seq, None)

    def seqs(self) -> list[int]:
        """Held seqs, in arrival order."""
        return list(self._frames)
