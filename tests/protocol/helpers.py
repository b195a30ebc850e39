"""Shared test material: message strategies, the vectors, and streams with counted injections."""

from __future__ import annotations

import json
import random
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hypothesis import strategies as st

from protocol import cobs
from protocol.compat import HANDSHAKE_IDS
from protocol.crc import frame_crc
from protocol.framing import encode_frame
from protocol.gen_vectors import build
from protocol.schema import (
    HEADER_FORMAT,
    MAX_WIRE_FRAME,
    PROTOCOL_VERSION,
    SCHEMA,
    TEXT,
    MessageSpec,
)

VECTORS_PATH = Path(__file__).resolve().parents[2] / "protocol" / "vectors.json"
UNUSED_ID = next(i for i in range(256) if i not in SCHEMA.by_id)
OVERSIZE_BYTES = 120  # longer than MAX_WIRE_FRAME - 1 encoded bytes


def load_vectors() -> list[dict[str, Any]]:
    """The vectors from protocol/vectors.json."""
    doc: dict[str, Any] = json.loads(VECTORS_PATH.read_text(encoding="utf-8"))
    return list(doc["vectors"])


def _utf8_fits(limit: int) -> st.SearchStrategy[str]:
    """Text whose UTF-8 encoding is at most `limit` bytes."""
    return st.text(max_size=limit).filter(lambda s: len(s.encode("utf-8")) <= limit)


ACK_ID = 0x81


def message_strategy(spec: MessageSpec) -> st.SearchStrategy[Any]:
    """Any valid instance of one message, fields drawn from their declared bounds."""
    kwargs: dict[str, st.SearchStrategy[Any]] = {}
    for f in spec.fields:
        if f.wire is TEXT:
            kwargs[f.name] = _utf8_fits(spec.max_text)
        else:
            kwargs[f.name] = st.integers(*f.info.bounds())
    return st.builds(spec.cls, **kwargs)


def raw_frame(msg_id: int, payload: bytes, seq: int = 7, version: int = PROTOCOL_VERSION) -> bytes:
    """Header, payload and a correct CRC, before COBS: lets tests build any header."""
    raw = struct.pack(HEADER_FORMAT, version, 0, seq, msg_id) + payload
    return raw + frame_crc(raw).to_bytes(2, "big")


def wire(raw: bytes) -> bytes:
    """COBS and delimiter around a raw frame."""
    return cobs.encode(raw) + b"\x00"


@dataclass
class InjectedStream:
    """A byte stream with the packets it must yield and the drops it must count."""

    data: bytearray = field(default_factory=bytearray)
    good: list[tuple[int, int, object]] = field(default_factory=list)
    expected: dict[str, int] = field(default_factory=dict)
    expected_total: int = 0

    def add_good(self, msg: object, seq: int, flags: int = 0) -> None:
        """A valid frame that must come out of the decoder."""
        self.data += encode_frame(msg, seq, flags)
        self.good.append((seq, flags, msg))

    def add_bad(self, data: bytes, counter: str | None) -> None:
        """One dropped frame ending in a delimiter; `counter` None when only the total is known."""
        if not data.endswith(b"\x00") or b"\x00" in data[:-1]:
            raise ValueError("an injection must be exactly one delimited segment")
        self.data += data
        self.expected_total += 1
        if counter is not None:
            self.expected[counter] = self.expected.get(counter, 0) + 1


def build_injected_stream(seed: int, rounds: int, *, exact_only: bool = False) -> InjectedStream:
    """Good vector messages interleaved with damage; `exact_only` keeps kinds of known counter."""
    rng = random.Random(seed)
    vectors = load_vectors()
    out = InjectedStream()
    injections = [
        _bad_crc,
        _bad_cobs,
        _bad_length,
        _bad_version,
        _unknown_id,
        _bad_payload,
        _oversize,
    ]
    if not exact_only:
        injections += [_flipped, _truncated, _garbage]
    for i in range(rounds):
        vec = vectors[i % len(vectors)]
        spec = SCHEMA.by_name[vec["message"]]
        msg = build(spec, vec["fields"])
        out.add_good(msg, vec["seq"], vec["flags"])
        if rng.random() < 0.2:
            out.add_good(msg, vec["seq"], vec["flags"])  # a duplicate is two good frames
        if rng.random() < 0.3:
            out.data += b"\x00" * rng.randint(1, 3)  # idle fill: never an error
        inject = injections[rng.randrange(len(injections))]
        data, counter = inject(rng, vec)
        out.add_bad(data, counter)
    return out


def _bad_crc(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """One raw byte changed before COBS, CRC kept: CRC-16 catches every single-byte error."""
    raw = bytearray.fromhex(vec["raw_hex"])
    pos = rng.randrange(len(raw))
    raw[pos] ^= rng.randint(1, 255)
    return wire(bytes(raw)), "bad_crc"


def _bad_cobs(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """First code byte pointing past the end of the frame."""
    enc = bytearray.fromhex(vec["frame_hex"])[:-1]
    enc[0] = rng.randint(len(enc) + 1, 255)
    return bytes(enc) + b"\x00", "bad_cobs"


def _bad_length(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """A valid COBS frame too short to hold header and CRC."""
    return wire(bytes.fromhex(vec["raw_hex"])[: rng.randint(0, 6)]), "bad_length"


def _bad_version(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """A well-formed frame of another protocol version (not HELLO/IDENTIFY: those are read)."""
    version = rng.choice([v for v in range(256) if v != PROTOCOL_VERSION])
    msg_id, payload = vec["id"], bytes.fromhex(vec["payload_hex"])
    if msg_id in HANDSHAKE_IDS:
        msg_id, payload = ACK_ID, b"\x01\x00\x01"
    return wire(raw_frame(msg_id, payload, version=version)), "bad_version"


def _unknown_id(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """A well-formed frame whose id the schema does not declare."""
    return wire(raw_frame(UNUSED_ID, bytes.fromhex(vec["payload_hex"]))), "unknown_id"


def _bad_payload(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """A known id with one byte too many (or invalid UTF-8 for a text message)."""
    spec = SCHEMA.by_id[vec["id"]]
    if spec.has_text:
        payload = bytes([0]) + b"\xff\xfe"
    else:
        payload = bytes.fromhex(vec["payload_hex"]) + bytes([rng.randint(0, 255)])
    return wire(raw_frame(spec.id, payload)), "bad_payload"


def _oversize(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """Non-zero bytes beyond the largest legal frame."""
    return bytes(rng.randint(1, 255) for _ in range(OVERSIZE_BYTES)) + b"\x00", "oversize"


def _flipped(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """An encoded byte replaced by another non-zero value: one drop, kind depends on the byte."""
    enc = bytearray.fromhex(vec["frame_hex"])[:-1]
    pos = rng.randrange(len(enc))
    enc[pos] = rng.choice([b for b in range(1, 256) if b != enc[pos]])
    return bytes(enc) + b"\x00", None


def _truncated(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """A frame cut short, then the delimiter: one drop."""
    enc = bytes.fromhex(vec["frame_hex"])[:-1]
    return enc[: rng.randint(1, len(enc) - 1)] + b"\x00", None


def _garbage(rng: random.Random, vec: dict[str, Any]) -> tuple[bytes, str | None]:
    """Random non-zero bytes, then a delimiter: one drop (oversize when long enough)."""
    n = rng.randint(1, 160)
    counter = "oversize" if n > MAX_WIRE_FRAME - 1 else None
    return bytes(rng.randint(1, 255) for _ in range(n)) + b"\x00", counter
