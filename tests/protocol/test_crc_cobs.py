"""CRC-16/IBM-3740 and COBS: catalogue values, fast == reference, round trips, 0xFF blocks."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import cobs
from protocol.crc import CHECK_VALUE, crc16, crc16_bitwise

NONZERO = st.binary(min_size=1).map(lambda b: bytes(x or 1 for x in b))


def test_crc_check_value() -> None:
    assert CHECK_VALUE == 0x29B1
    assert crc16(b"123456789") == 0x29B1
    assert crc16_bitwise(b"123456789") == 0x29B1


def test_crc_of_frame_with_its_crc_big_endian_is_zero() -> None:
    data = b"\x01\x00\x10\x00\x90hello"
    assert crc16(data + crc16(data).to_bytes(2, "big")) == 0


def test_crc_continues_from_a_previous_value() -> None:
    assert crc16(b"56789", crc16(b"1234")) == 0x29B1


@settings(max_examples=300)
@given(st.binary(max_size=300))
def test_crc_fast_equals_bitwise(data: bytes) -> None:
    assert crc16(data) == crc16_bitwise(data)


@settings(max_examples=300)
@given(st.binary(min_size=1, max_size=100), st.data())
def test_crc_catches_every_single_byte_error(data: bytes, draw: st.DataObject) -> None:
    pos = draw.draw(st.integers(0, len(data) - 1))
    delta = draw.draw(st.integers(1, 255))
    bad = bytearray(data)
    bad[pos] ^= delta
    assert crc16(bytes(bad)) != crc16(data)


@pytest.mark.parametrize(
    ("raw", "enc"),
    [
        (b"", b"\x01"),
        (b"\x00", b"\x01\x01"),
        (b"\x00\x00", b"\x01\x01\x01"),
        (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
        (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
        (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
        # 254 non-zero bytes fill a 0xFF block; an empty final block follows.
        (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255)) + b"\x01"),
        (bytes(range(1, 255)) + b"\x00", b"\xff" + bytes(range(1, 255)) + b"\x01\x01"),
        (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    ],
)
def test_cobs_known_encodings(raw: bytes, enc: bytes) -> None:
    # Published examples (Cheshire & Baker; Wikipedia's table) and the 0xFF block edge.
    assert cobs.encode(raw) == enc
    assert cobs.decode(enc) == raw


@settings(max_examples=400)
@given(st.binary(max_size=2000))
def test_cobs_round_trip(data: bytes) -> None:
    enc = cobs.encode(data)
    assert b"\x00" not in enc
    assert len(enc) <= len(data) + 1 + len(data) // 254
    assert cobs.decode(enc) == data


@settings(max_examples=200)
@given(NONZERO, st.lists(st.integers(0, 1200), max_size=6))
def test_cobs_round_trip_long_runs_without_zeros(run: bytes, zeros_at: list[int]) -> None:
    # Long zero-free runs cross 0xFF blocks; scattered zeros exercise the block after them.
    data = bytearray((run * (1300 // len(run) + 1))[:1300])
    for pos in zeros_at:
        data[pos] = 0
    assert cobs.decode(cobs.encode(bytes(data))) == bytes(data)


@pytest.mark.parametrize(
    "bad",
    [b"", b"\x00", b"\x03\x11", b"\x02\x11\x00", b"\x05\x11\x22", b"\xff" + b"\x01" * 10],
)
def test_cobs_malformed_raises_cobs_error(bad: bytes) -> None:
    with pytest.raises(cobs.CobsError):
        cobs.decode(bad)


@settings(max_examples=500)
@given(st.binary(max_size=600))
def test_cobs_decode_never_raises_anything_else(data: bytes) -> None:
    try:
        out = cobs.decode(data)
    except cobs.CobsError:
        return
    # Every block costs a code byte, so a decoding is always shorter than its input; and what
    # decodes round-trips through the canonical encoding.
    assert len(out) < len(data)
    assert cobs.decode(cobs.encode(out)) == out
