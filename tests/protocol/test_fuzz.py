"""Fuzz the decoder with random and mutated buffers: never an exception, every segment accounted.

Invariant checked on each buffer (which always ends in a delimiter): every non-empty segment
between delimiters is either one good packet or exactly one counted drop.
"""

from __future__ import annotations

import random

import pytest

from protocol import FrameDecoder, encode_frame
from protocol.schema import SCHEMA
from tests.protocol.helpers import load_vectors

FAST_BUFFERS = 100_000
SLOW_BUFFERS = 2_000_000
FRAMES = [bytes.fromhex(v["frame_hex"]) for v in load_vectors()]


def _mutate(rng: random.Random, data: bytearray) -> None:
    """Apply one random edit: flip, overwrite, insert, delete, duplicate or splice a frame."""
    op = rng.randrange(6)
    pos = rng.randrange(len(data))
    if op == 0:
        data[pos] ^= 1 << rng.randrange(8)
    elif op == 1:
        data[pos] = rng.randrange(256)
    elif op == 2:
        data[pos:pos] = rng.randbytes(rng.randint(1, 8))
    elif op == 3:
        del data[pos : pos + rng.randint(1, 8)]
    elif op == 4:
        data[pos:pos] = data[pos : pos + rng.randint(1, 30)]
    else:
        data[pos:pos] = rng.choice(FRAMES)


def _buffer(rng: random.Random) -> bytes:
    """Half pure noise (zero-heavy or not), half vector frames with a few mutations."""
    if rng.random() < 0.5:
        n = rng.randint(0, 120)
        if rng.random() < 0.5:
            return rng.randbytes(n) + b"\x00"
        return bytes(rng.choice((0, 0, rng.randrange(256))) for _ in range(n)) + b"\x00"
    data = bytearray(b"".join(rng.choice(FRAMES) for _ in range(rng.randint(1, 4))))
    for _ in range(rng.randint(1, 4)):
        if data:
            _mutate(rng, data)
    return bytes(data) + b"\x00"


def _segments(data: bytes) -> int:
    """Non-empty segments between delimiters (the buffer ends in one)."""
    return sum(1 for s in data.split(b"\x00") if s)


def _run(seed: int, count: int) -> int:
    """Decode `count` buffers; return how many packets survived (to show mutation leaves some)."""
    rng = random.Random(seed)
    survived = 0
    for _ in range(count):
        data = _buffer(rng)
        dec = FrameDecoder()
        packets = dec.feed(data)
        assert len(packets) == dec.frames_ok
        assert dec.frames_ok + dec.drops.total() == _segments(data), data.hex()
        for p in packets:
            assert 0 <= p.seq <= 0xFFFF
            assert 0 <= p.flags <= 0xFF
            assert type(p.message) in SCHEMA.by_cls
            _reencode_if_in_range(p.message, p.seq, p.flags)
        survived += len(packets)
    return survived


def _reencode_if_in_range(msg: object, seq: int, flags: int) -> None:
    """A decoded message within its ranges re-encodes and decodes to itself."""
    try:
        frame = encode_frame(msg, seq, flags)
    except ValueError:
        return  # decode does not range-check; such values are the receiver's to refuse
    [again] = FrameDecoder().feed(frame)
    assert again.message == msg


def test_fuzz_100k_buffers() -> None:
    assert _run(seed=20240611, count=FAST_BUFFERS) > 1000


@pytest.mark.slow
def test_fuzz_2m_buffers() -> None:
    assert _run(seed=7, count=SLOW_BUFFERS) > 20_000
