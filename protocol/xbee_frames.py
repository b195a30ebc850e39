"""Digi XBee API frames, API mode 1 (AP=1) and mode 2 (AP=2, escaped): pure, no I/O.

    frame = 0x7E | length u16 BE | frame data | checksum
    checksum = 0xFF - (sum of frame data & 0xFF)

In mode 2 every byte after the start delimiter that is 0x7E, 0x7D, 0x11 or 0x13 is sent as 0x7D
then byte ^ 0x20; length and checksum are computed on the unescaped bytes. The host transport and
the emulated radio module share this module.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field

START_DELIMITER = 0x7E
ESCAPE = 0x7D
ESCAPE_XOR = 0x20
ESCAPED_BYTES = frozenset((0x7E, 0x7D, 0x11, 0x13))
MAX_RF_PAYLOAD = 84  # bytes of RF data in one unicast, no encryption, no fragmentation
MAX_FRAME_DATA = 256  # bigger lengths are corruption; real modules stay far below this
BROADCAST_RADIUS_MAX_HOPS = 0
UNKNOWN_ADDR16 = 0xFFFE
TX_OPTIONS_DEFAULT = 0x00
RX_OPTIONS_ACKNOWLEDGED = 0x01

_TX_HEADER = struct.Struct(">BBQHBB")  # type, frame id, addr64, addr16, radius, options
_RX_HEADER = struct.Struct(">BQHB")  # type, addr64, addr16, options
_TX_STATUS = struct.Struct(">BBHBBB")  # type, frame id, addr16, retries, delivery, discovery


class FrameType(enum.IntEnum):
    """API frame types this link uses."""

    TRANSMIT_REQUEST = 0x10
    TRANSMIT_STATUS = 0x8B
    RECEIVE_PACKET = 0x90


class DeliveryStatus(enum.IntEnum):
    """Delivery status of a Transmit Status (0x8B) frame, as Digi names them."""

    SUCCESS = 0x00
    MAC_ACK_FAILURE = 0x01
    CCA_FAILURE = 0x02
    INVALID_DESTINATION_ENDPOINT = 0x15
    NETWORK_ACK_FAILURE = 0x21
    NOT_JOINED = 0x22
    SELF_ADDRESSED = 0x23
    ADDRESS_NOT_FOUND = 0x24
    ROUTE_NOT_FOUND = 0x25
    BROADCAST_RELAY_NOT_HEARD = 0x26
    INVALID_BINDING_INDEX = 0x2B
    RESOURCE_ERROR = 0x2C
    APS_BROADCAST = 0x2D
    APS_UNICAST_NO_ENCRYPTION = 0x2E
    INTERNAL_RESOURCE_ERROR = 0x31
    NO_FREE_BUFFERS = 0x32
    PAYLOAD_TOO_LARGE = 0x74
    INDIRECT_UNREQUESTED = 0x75


def status_name(code: int) -> str:
    """Counter-friendly name of a delivery status, also for codes Digi added later."""
    try:
        return DeliveryStatus(code).name.lower()
    except ValueError:
        return f"status_0x{code:02x}"


def checksum(frame_data: bytes) -> int:
    """XBee checksum of unescaped frame data."""
    return 0xFF - (sum(frame_data) & 0xFF)


def escape(data: bytes) -> bytes:
    """Mode 2 escaping of the bytes after the start delimiter."""
    out = bytearray()
    for byte in data:
        if byte in ESCAPED_BYTES:
            out += bytes((ESCAPE, byte ^ ESCAPE_XOR))
        else:
            out.append(byte)
    return bytes(out)


def encode_api_frame(frame_data: bytes, escaped: bool) -> bytes:
    """Frame data → one API frame on the UART (escaped for API mode 2)."""
    if not 0 < len(frame_data) <= MAX_FRAME_DATA:
        raise ValueError(f"frame data of {len(frame_data)} bytes outside [1, {MAX_FRAME_DATA}]")
    body = len(frame_data).to_bytes(2, "big") + frame_data + bytes((checksum(frame_data),))
    return bytes((START_DELIMITER,)) + (escape(body) if escaped else body)


@dataclass(frozen=True, slots=True)
class TransmitRequest:
    """0x10: send RF data to a 64-bit address."""

    frame_id: int
    dest_addr64: int
    data: bytes
    dest_addr16: int = UNKNOWN_ADDR16
    radius: int = BROADCAST_RADIUS_MAX_HOPS
    options: int = TX_OPTIONS_DEFAULT

    def frame_data(self) -> bytes:
        """Unescaped frame data, type byte first."""
        head = _TX_HEADER.pack(
            FrameType.TRANSMIT_REQUEST,
            self.frame_id,
            self.dest_addr64,
            self.dest_addr16,
            self.radius,
            self.options,
        )
        return head + self.data

    @classmethod
    def parse(cls, frame_data: bytes) -> TransmitRequest:
        """Frame data → request; ValueError if too short."""
        _, frame_id, addr64, addr16, radius, options = _unpack(_TX_HEADER, frame_data)
        return cls(frame_id, addr64, frame_data[_TX_HEADER.size :], addr16, radius, options)


@dataclass(frozen=True, slots=True)
class ReceivePacket:
    """0x90: RF data received from a 64-bit address."""

    src_addr64: int
    data: bytes
    src_addr16: int = UNKNOWN_ADDR16
    options: int = RX_OPTIONS_ACKNOWLEDGED

    def frame_data(self) -> bytes:
        """Unescaped frame data, type byte first."""
        head = _RX_HEADER.pack(
            FrameType.RECEIVE_PACKET, self.src_addr64, self.src_addr16, self.options
        )
        return head + self.data

    @classmethod
    def parse(cls, frame_data: bytes) -> ReceivePacket:
        """Frame data → packet; ValueError if too short."""
        _, addr64, addr16, options = _unpack(_RX_HEADER, frame_data)
        return cls(addr64, frame_data[_RX_HEADER.size :], addr16, options)


@dataclass(frozen=True, slots=True)
class TransmitStatus:
    """0x8B: what became of the Transmit Request with the same frame id."""

    frame_id: int
    retries: int
    delivery: int
    discovery: int = 0
    dest_addr16: int = UNKNOWN_ADDR16

    def frame_data(self) -> bytes:
        """Unescaped frame data, type byte first."""
        return _TX_STATUS.pack(
            FrameType.TRANSMIT_STATUS,
            self.frame_id,
            self.dest_addr16,
            self.retries,
            self.delivery,
            self.discovery,
        )

    @classmethod
    def parse(cls, frame_data: bytes) -> TransmitStatus:
        """Frame data → status; ValueError if too short."""
        _, frame_id, addr16, retries, delivery, discovery = _unpack(_TX_STATUS, frame_data)
        return cls(frame_id, retries, delivery, discovery, addr16)


def _unpack(layout: struct.Struct, frame_data: bytes) -> tuple[int, ...]:
    """Unpack a fixed header, with a clear error when the frame is short."""
    if len(frame_data) < layout.size:
        raise ValueError(f"frame of {len(frame_data)} bytes, header needs {layout.size}")
    return layout.unpack_from(frame_data)


class _Stage(enum.Enum):
    """Where the decoder is inside an API frame."""

    HUNT = "hunt"
    LENGTH = "length"
    DATA = "data"


@dataclass
class ApiDecoderStats:
    """Bytes and frames the API decoder threw away, by reason."""

    frames_ok: int = 0
    bad_checksum: int = 0
    bad_length: int = 0
    truncated: int = 0
    junk_bytes: int = 0


@dataclass
class ApiFrameDecoder:
    """Incremental API frame decoder: feed UART chunks, get unescaped frame data back."""

    escaped: bool
    stats: ApiDecoderStats = field(default_factory=ApiDecoderStats)
    _stage: _Stage = _Stage.HUNT
    _buf: bytearray = field(default_factory=bytearray)
    _need: int = 0
    _escape_next: bool = False

    def feed(self, data: bytes) -> list[bytes]:
        """Consume bytes; return the frame data (type byte first) of every good frame."""
        out: list[bytes] = []
        for byte in data:
            frame = self._step(byte)
            if frame is not None:
                out.append(frame)
        return out

    def _step(self, byte: int) -> bytes | None:
        """Advance by one UART byte."""
        if byte == START_DELIMITER and (self.escaped or self._stage is _Stage.HUNT):
            # In mode 2 a bare 0x7E always starts a frame, so a cut frame resyncs here.
            if self._stage is not _Stage.HUNT:
                self.stats.truncated += 1
            self._restart(_Stage.LENGTH, 2)
            return None
        if self._stage is _Stage.HUNT:
            self.stats.junk_bytes += 1
            return None
        if self.escaped:
            if byte == ESCAPE:
                self._escape_next = True
                return None
            if self._escape_next:
                byte ^= ESCAPE_XOR
                self._escape_next = False
        self._buf.append(byte)
        if len(self._buf) < self._need:
            return None
        return self._stage_done()

    def _stage_done(self) -> bytes | None:
        """The bytes of the current stage are in: move on or finish the frame."""
        if self._stage is _Stage.LENGTH:
            length = int.from_bytes(self._buf, "big")
            if not 0 < length <= MAX_FRAME_DATA:
                self.stats.bad_length += 1
                self._stage = _Stage.HUNT
                return None
            self._restart(_Stage.DATA, length + 1)
            return None
        frame_data, check = bytes(self._buf[:-1]), self._buf[-1]
        self._stage = _Stage.HUNT
        if checksum(frame_data) != check:
            self.stats.bad_checksum += 1
            return None
        self.stats.frames_ok += 1
        return frame_data

    def _restart(self, stage: _Stage, need: int) -> None:
        """Begin collecting `need` bytes for `stage`."""
        self._stage = stage
        self._need = need
        self._buf.clear()
        self._escape_next = False
