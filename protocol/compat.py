"""HELLO and IDENTIFY across protocol versions, so a refusal can always be shown (§7).

From version 2 on, HELLO and IDENTIFY keep their id and only ever grow: a field is appended,
never moved or removed. A receiver that sees either message in a frame of another version
decodes the fields it knows from the front of the payload, takes absent trailing fields as 0
and ignores extra bytes. Version 1 framed with CRC-16/IBM-3740 (zero residue); it is still
recognised for these two messages, and a controller answers a version-1 HELLO in version-1
framing so that a version-1 host can read who it is talking to.
"""

from __future__ import annotations

import struct
from typing import Any

from protocol import cobs
from protocol.codec import spec_of
from protocol.crc import CRC_INIT, crc16
from protocol.messages import Hello, Identify
from protocol.schema import CRC_SIZE, HEADER_FORMAT, HEADER_SIZE, SCHEMA, TEXT

LEGACY_VERSION = 1
_HEADER = struct.Struct(HEADER_FORMAT)
HANDSHAKE_IDS = frozenset(SCHEMA.by_cls[c].id for c in (Hello, Identify))
# Payload bytes of HELLO and IDENTIFY in version 1: the prefix every version starts with.
V1_PAYLOAD_SIZE = {SCHEMA.by_cls[Hello].id: 5, SCHEMA.by_cls[Identify].id: 35}


def legacy_frame_ok(raw: bytes) -> bool:
    """Whether a raw frame passes version 1's check and is a version-1 HELLO or IDENTIFY."""
    return (
        len(raw) >= HEADER_SIZE + CRC_SIZE
        and raw[0] == LEGACY_VERSION
        and raw[4] in HANDSHAKE_IDS
        and crc16(raw, CRC_INIT) == 0
    )


def decode_handshake(msg_id: int, payload: bytes) -> Any | None:
    """A HELLO/IDENTIFY of any version from its payload; None if shorter than version 1's."""
    if len(payload) < V1_PAYLOAD_SIZE.get(msg_id, 1 << 16):
        return None
    spec = SCHEMA.by_id[msg_id]
    values: list[int] = []
    offset = 0
    for f in spec.fields:
        if f.wire is TEXT:
            return None
        size = f.wire.size
        if offset + size > len(payload):
            values.append(0)
        else:
            values.append(struct.unpack_from("<" + f.wire.code, payload, offset)[0])
        offset += size
    return spec.cls(*values)


def encode_v1(message: object, seq: int, flags: int) -> bytes:
    """A HELLO or IDENTIFY framed as version 1 (its first fields, CRC-16/IBM-3740)."""
    spec = spec_of(message)
    if spec.id not in V1_PAYLOAD_SIZE:
        raise ValueError(f"{spec.name} has no version-1 form")
    values = [getattr(message, f.name) for f in spec.fields]
    payload = struct.pack(spec.struct_format, *values)[: V1_PAYLOAD_SIZE[spec.id]]
    raw = _HEADER.pack(LEGACY_VERSION, flags, seq, spec.id) + payload
    return cobs.encode(raw + crc16(raw).to_bytes(2, "big")) + b"\x00"
