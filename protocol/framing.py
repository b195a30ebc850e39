"""Frames on the wire: header + payload + CRC, COBS-encoded, delimited by 0x00.

    wire  = COBS(raw) 0x00
    raw   = version u8 | flags u8 | seq u16 LE | msg_id u8 | payload | crc16 BE
    crc16 = CRC-16/GENIBUS over version..payload, sent most significant byte first

Sending the CRC big-endian lets a receiver check the whole raw frame in one call: the CRC
register run over data and its own CRC ends at the constant FRAME_RESIDUE. HELLO and IDENTIFY
of other versions are still decoded (protocol.compat). The decoder never raises; it counts
and drops.
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass, field

from protocol import cobs
from protocol.codec import RAW_DECODERS, PayloadError, encode_payload
from protocol.compat import HANDSHAKE_IDS, LEGACY_VERSION, decode_handshake, legacy_frame_ok
from protocol.crc import CRC_INIT, FRAME_RESIDUE, frame_crc
from protocol.schema import (
    CRC_SIZE,
    HEADER_FORMAT,
    HEADER_SIZE,
    MAX_RAW_FRAME,
    MAX_WIRE_FRAME,
    PROTOCOL_VERSION,
    Flag,
)

DELIMITER = b"\x00"
_HEADER = struct.Struct(HEADER_FORMAT)
_HEADER_UNPACK = _HEADER.unpack_from
_crc_hqx = binascii.crc_hqx  # the CRC-16 register seeded with 0xFFFF (see protocol.crc)
_MIN_RAW = HEADER_SIZE + CRC_SIZE


@dataclass(slots=True)
class Packet:
    """One decoded frame: header fields and the typed message."""

    seq: int
    flags: int
    message: object
    version: int = PROTOCOL_VERSION  # another only for a HELLO/IDENTIFY read across versions


@dataclass
class DropCounters:
    """Why frames were dropped; every dropped frame lands in exactly one counter."""

    bad_crc: int = 0
    bad_cobs: int = 0
    bad_length: int = 0
    bad_version: int = 0
    unknown_id: int = 0
    bad_payload: int = 0
    oversize: int = 0

    def total(self) -> int:
        """All dropped frames."""
        return sum(vars(self).values())


def encode_frame(message: object, seq: int, flags: int = Flag.NONE) -> bytes:
    """Message → wire bytes, trailing delimiter included; ValueError if it cannot be sent."""
    if not 0 <= seq <= 0xFFFF:
        raise ValueError(f"seq={seq} outside [0, 65535]")
    msg_id, payload = encode_payload(message)
    raw = _HEADER.pack(PROTOCOL_VERSION, int(flags), seq, msg_id) + payload
    raw += frame_crc(raw).to_bytes(2, "big")
    if len(raw) > MAX_RAW_FRAME:
        raise ValueError(f"frame of {len(raw)} bytes exceeds {MAX_RAW_FRAME}")
    return cobs.encode(raw) + DELIMITER


@dataclass
class FrameDecoder:
    """Incremental decoder: feed any chunks of the byte stream, get the packets in them."""

    max_wire_frame: int = MAX_WIRE_FRAME
    drops: DropCounters = field(default_factory=DropCounters)
    frames_ok: int = 0
    bytes_in: int = 0
    last_unknown_id: int | None = None  # the id of the last frame dropped as unknown_id
    _buf: bytearray = field(default_factory=bytearray)
    _discarding: bool = False

    def feed(self, data: bytes) -> list[Packet]:
        """Consume bytes; return every good packet completed by them, in order."""
        self.bytes_in += len(data)
        if 0 not in data:  # an int search is memchr; a bytes needle costs 5x more here
            self._buf += data
            self._check_oversize()
            return []
        # Split the caller's bytes directly when nothing is pending (every datagram transport).
        segments = (self._buf + data if self._buf else data).split(DELIMITER)
        self._buf = bytearray(segments.pop())
        out: list[Packet] = []
        limit = self.max_wire_frame - 1
        for enc in segments:
            if self._discarding:
                # The tail of an oversize frame: its delimiter ends the discard.
                self._discarding = False
            elif len(enc) > limit:
                self.drops.oversize += 1
            elif enc:  # back-to-back delimiters are idle fill, not errors
                packet = self._decode(enc)
                if packet is not None:
                    out.append(packet)
        if len(self._buf) > limit:
            self._check_oversize()
        return out

    def reset(self) -> None:
        """Forget any partial frame (after a reconnect)."""
        self._buf.clear()
        self._discarding = False

    def _check_oversize(self) -> None:
        """Drop a partial frame that has already outgrown the largest legal frame."""
        if len(self._buf) > self.max_wire_frame - 1:
            if not self._discarding:
                self.drops.oversize += 1
            self._discarding = True
            self._buf.clear()

    def _decode(self, enc: bytes | bytearray) -> Packet | None:
        """One delimited frame → packet, or None with the reason counted."""
        try:
            raw = cobs.decode(enc)
        except cobs.CobsError:
            self.drops.bad_cobs += 1
            return None
        if len(raw) < _MIN_RAW:
            self.drops.bad_length += 1
            return None
        # CRC sent big-endian: the register over data and its own CRC ends at the residue.
        if _crc_hqx(raw, CRC_INIT) != FRAME_RESIDUE and not legacy_frame_ok(raw):
            self.drops.bad_crc += 1
            return None
        version, flags, seq, msg_id = _HEADER_UNPACK(raw)
        if version != PROTOCOL_VERSION:
            return self._foreign(version, flags, seq, msg_id, raw)
        decode = RAW_DECODERS.get(msg_id)
        if decode is None:
            self.drops.unknown_id += 1
            self.last_unknown_id = msg_id
            return None
        try:
            msg = decode(raw)
        except PayloadError:
            self.drops.bad_payload += 1
            return None
        self.frames_ok += 1
        return Packet(seq, flags, msg)

    def _foreign(
        self, version: int, flags: int, seq: int, msg_id: int, raw: bytes
    ) -> Packet | None:
        """Another version's frame: only HELLO and IDENTIFY are read, to show the mismatch."""
        if msg_id not in HANDSHAKE_IDS or (version == LEGACY_VERSION and not legacy_frame_ok(raw)):
            self.drops.bad_version += 1
            return None
        msg = decode_handshake(msg_id, raw[HEADER_SIZE : len(raw) - CRC_SIZE])
        if msg is None:
            self.drops.bad_payload += 1
            return None
        self.frames_ok += 1
        return Packet(seq, flags, msg, version)
