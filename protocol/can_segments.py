"""Wire frames cut into CAN frames and glued back together: pure, no I/O.

Every CAN frame's first byte is a header:

    bit 7 START   first segment of a wire frame
    bit 6 END     last segment of a wire frame
    bits 5..0     segment counter, per direction, mod 64, +1 on every CAN frame sent

followed by up to 7 data bytes (63 with CAN FD). The receiver uses the counter to notice lost and
late segments: a gap or a START before the previous END throws the partial frame away, and so does
age (a partial frame older than 50 ms is stale). The host transport and the simulated controller
node both use this module, as the C firmware's CAN driver does the same in C.
"""

from __future__ import annotations

from dataclasses import dataclass, field

START = 0x80
END = 0x40
COUNTER_MASK = 0x3F
COUNTER_MOD = 64
CLASSIC_DATA_BYTES = 7  # 8-byte CAN payload minus the header
FD_DATA_BYTES = 63  # 64-byte CAN FD payload minus the header
PARTIAL_TIMEOUT_S = 0.050
# A counter behind the expected one by less than half the ring is a late segment, not a gap.
_HALF_RING = COUNTER_MOD // 2


class Segmenter:
    """Cut wire frames into CAN payloads, numbering every CAN frame of one direction."""

    def __init__(self, data_bytes: int = CLASSIC_DATA_BYTES) -> None:
        if not 1 <= data_bytes <= FD_DATA_BYTES:
            raise ValueError(f"data_bytes={data_bytes} outside [1, {FD_DATA_BYTES}]")
        self.data_bytes = data_bytes
        self.counter = 0

    def split(self, frame: bytes) -> list[bytes]:
        """One wire frame → CAN payloads (header byte + data), in sending order."""
        if not frame:
            raise ValueError("cannot segment an empty frame")
        step = self.data_bytes
        chunks = [frame[i : i + step] for i in range(0, len(frame), step)]
        out = []
        for index, chunk in enumerate(chunks):
            header = self.counter
            if index == 0:
                header |= START
            if index == len(chunks) - 1:
                header |= END
            out.append(bytes((header,)) + chunk)
            self.counter = (self.counter + 1) % COUNTER_MOD
        return out


@dataclass
class ReassemblyStats:
    """What the reassembler saw go wrong; names match the transport's `stats.extra` keys."""

    can_frames_in: int = 0
    can_frames_delivered: int = 0
    can_lost_segments: int = 0
    can_reassembly_discards: int = 0
    can_reordered: int = 0
    can_timeouts: int = 0
    can_orphan_segments: int = 0
    can_empty_segments: int = 0

    def as_dict(self) -> dict[str, int]:
        """Counters as a plain dict."""
        return dict(vars(self))


@dataclass
class Reassembler:
    """Glue CAN payloads back into wire frames; every damaged frame is counted, none delivered."""

    timeout_s: float = PARTIAL_TIMEOUT_S
    stats: ReassemblyStats = field(default_factory=ReassemblyStats)
    _expected: int | None = None
    _partial: bytearray | None = None
    _started_s: float = 0.0

    def feed(self, payload: bytes, now_s: float) -> bytes | None:
        """One CAN payload → a completed wire frame, or None (incomplete or dropped)."""
        self.stats.can_frames_in += 1
        if not payload:
            self.stats.can_empty_segments += 1
            return None
        self.expire(now_s)
        header = payload[0]
        counter = header & COUNTER_MASK
        if not self._check_counter(counter):
            return None
        self._expected = (counter + 1) % COUNTER_MOD
        return self._take(header, payload[1:], now_s)

    def expire(self, now_s: float) -> None:
        """Drop a partial frame that has waited longer than the timeout."""
        if self._partial is not None and now_s - self._started_s > self.timeout_s:
            self._partial = None
            self.stats.can_timeouts += 1

    def reset(self) -> None:
        """Forget the counter and any partial frame (after a reconnect)."""
        self._expected = None
        self._partial = None

    @property
    def pending(self) -> bool:
        """True while a partial frame waits for its remaining segments."""
        return self._partial is not None

    def _check_counter(self, counter: int) -> bool:
        """Account for a gap or a late segment; False if the segment must be ignored."""
        if self._expected is None or counter == self._expected:
            return True
        behind = (self._expected - counter) % COUNTER_MOD
        if behind <= _HALF_RING:
            # Older than what we expect: it was overtaken, and its frame is already gone.
            self.stats.can_reordered += 1
            return False
        self.stats.can_lost_segments += (counter - self._expected) % COUNTER_MOD
        self._discard_partial()
        return True

    def _take(self, header: int, data: bytes, now_s: float) -> bytes | None:
        """Add an in-sequence segment to the partial frame; return the frame on END."""
        if header & START:
            self._discard_partial()
            self._partial = bytearray()
            self._started_s = now_s
        elif self._partial is None:
            # The START of this frame never arrived: nothing to add it to.
            self.stats.can_orphan_segments += 1
            return None
        self._partial += data
        if not header & END:
            return None
        frame = bytes(self._partial)
        self._partial = None
        self.stats.can_frames_delivered += 1
        return frame

    def _discard_partial(self) -> None:
        """Throw away an unfinished frame, counting it."""
        if self._partial is not None:
            self._partial = None
            self.stats.can_reassembly_discards += 1


# ---- identifiers (PROTOCOL.md §11, CAN) ----------------------------------------

HOST_TO_CONTROLLER_BASE_ID = 0x200
CONTROLLER_TO_HOST_BASE_ID = 0x280
NODE_ID_MIN = 1
NODE_ID_MAX = 127
DEFAULT_BITRATE = 500_000
CAN_ERR_BUSOFF = 0x0000_0040  # SocketCAN error class bit in an error frame's id


def check_node_id(node_id: object) -> int:
    """1..127; ValueError otherwise."""
    if isinstance(node_id, bool) or not isinstance(node_id, int):
        raise ValueError(f"node_id must be an integer in [1, 127], got {node_id!r}")
    if not NODE_ID_MIN <= node_id <= NODE_ID_MAX:
        raise ValueError(f"node_id={node_id} outside [{NODE_ID_MIN}, {NODE_ID_MAX}]")
    return node_id


def ids_for(node_id: int) -> tuple[int, int]:
    """(host → controller id, controller → host id) of a node."""
    return HOST_TO_CONTROLLER_BASE_ID + node_id, CONTROLLER_TO_HOST_BASE_ID + node_id
