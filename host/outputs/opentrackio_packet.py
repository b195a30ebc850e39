"""OpenTrackIO datagrams: the 16-byte header, Fletcher-16, and segmentation of large samples.

Layout (big-endian), as OpenTrackIO 1.0 defines it and Unreal's LiveLink source reads it:

    0  u32  identifier "OTrk"
    4  u8   reserved (0)
    5  u8   encoding: 0x01 JSON, 0x02 CBOR
    6  u16  sequence number: one per sample, the same in every segment of it
    8  u32  segment offset: where this segment's payload starts within the sample's payload
   12  u16  bit 15: last segment; bits 0-14: this segment's payload length
   14  u16  Fletcher-16 (mod 255) of bytes 0-13 and the segment's payload, (c1 << 8) | c0

Pure: no I/O, so the sender, the tests and any receiver share one implementation.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

IDENTIFIER = b"OTrk"
HEADER = struct.Struct(">4sBBHIHH")
HEADER_BYTES = HEADER.size  # 16
LAST_SEGMENT = 0x8000
MAX_SEGMENT_PAYLOAD = 0x7FFF  # the length field's 15 bits
DEFAULT_MTU_BYTES = 1500  # one Ethernet frame, as OpenTrackIO recommends
UDP_IP_OVERHEAD_BYTES = 28  # IPv4 (20) + UDP (8) headers inside the MTU
FLETCHER_MODULUS = 255


class Encoding(IntEnum):
    """Payload encodings of the header's byte 5."""

    JSON = 0x01
    CBOR = 0x02


@dataclass(frozen=True)
class Segment:
    """One decoded datagram."""

    encoding: int
    sequence: int
    offset: int
    last: bool
    payload: bytes


def fletcher16(data: bytes) -> int:
    """Fletcher-16 over `data`: (sum of sums mod 255) << 8 | (sum mod 255)."""
    c0 = c1 = 0
    for byte in data:
        c0 = (c0 + byte) % FLETCHER_MODULUS
        c1 = (c1 + c0) % FLETCHER_MODULUS
    return (c1 << 8) | c0


def encode_segment(
    encoding: Encoding, sequence: int, offset: int, last: bool, payload: bytes
) -> bytes:
    """One datagram: header with checksum, then the payload."""
    if len(payload) > MAX_SEGMENT_PAYLOAD:
        raise ValueError(f"segment payload of {len(payload)} bytes exceeds {MAX_SEGMENT_PAYLOAD}")
    length = len(payload) | (LAST_SEGMENT if last else 0)
    head = HEADER.pack(IDENTIFIER, 0, int(encoding), sequence & 0xFFFF, offset, length, 0)
    checksum = fletcher16(head[: HEADER_BYTES - 2] + payload)
    return head[: HEADER_BYTES - 2] + checksum.to_bytes(2, "big") + payload


def segment_payload(
    encoding: Encoding, sequence: int, payload: bytes, mtu_bytes: int = DEFAULT_MTU_BYTES
) -> list[bytes]:
    """The datagrams that carry one sample, each fitting `mtu_bytes` with its IP/UDP headers."""
    room = min(mtu_bytes - UDP_IP_OVERHEAD_BYTES - HEADER_BYTES, MAX_SEGMENT_PAYLOAD)
    if room < 1:
        raise ValueError(f"an MTU of {mtu_bytes} bytes leaves no room for a payload")
    offsets = range(0, max(len(payload), 1), room)
    return [
        encode_segment(encoding, sequence, at, at + room >= len(payload), payload[at : at + room])
        for at in offsets
    ]


def decode_segment(datagram: bytes) -> Segment:
    """Parse and check one datagram; ValueError says what is wrong."""
    if len(datagram) < HEADER_BYTES:
        raise ValueError(f"{len(datagram)} bytes: shorter than the 16-byte header")
    ident, _reserved, encoding, sequence, offset, length, checksum = HEADER.unpack_from(datagram)
    if ident != IDENTIFIER:
        raise ValueError(f"identifier {ident!r} is not {IDENTIFIER!r}")
    size = length & MAX_SEGMENT_PAYLOAD
    payload = datagram[HEADER_BYTES : HEADER_BYTES + size]
    if len(payload) != size:
        raise ValueError(f"header says {size} payload bytes, datagram has {len(payload)}")
    expected = fletcher16(datagram[: HEADER_BYTES - 2] + payload)
    if checksum != expected:
        raise ValueError(f"checksum {checksum:#06x}, computed {expected:#06x}")
    return Segment(encoding, sequence, offset, bool(length & LAST_SEGMENT), payload)


class Reassembler:
    """Joins the segments of one sequence number; a gap or a new sequence drops the partial one."""

    def __init__(self) -> None:
        self._sequence: int | None = None
        self._parts: dict[int, bytes] = {}
        self.dropped = 0  # samples lost to a missing segment

    def feed(self, segment: Segment) -> bytes | None:
        """The whole payload once its last segment arrives with nothing missing, else None."""
        if segment.sequence != self._sequence:
            self.dropped += bool(self._parts)
            self._sequence, self._parts = segment.sequence, {}
        self._parts[segment.offset] = segment.payload
        if not segment.last:
            return None
        payload, at = b"", 0
        while at in self._parts:
            part = self._parts.pop(at)
            payload += part
            at += len(part)
            if at == segment.offset + len(segment.payload):
                self._sequence, self._parts = None, {}
                return payload
        self.dropped += 1
        self._sequence, self._parts = None, {}
        return None
