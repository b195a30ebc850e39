"""Consistent Overhead Byte Stuffing: frames without 0x00, so 0x00 can delimit them."""

from __future__ import annotations

_MAX_BLOCK = 0xFE  # data bytes one code byte can cover before a 0xFF code splits the block
_CODE = [bytes((n,)) for n in range(256)]  # code byte objects, built once for the fast path


class CobsError(ValueError):
    """The bytes are not a valid COBS encoding."""


def encode(data: bytes) -> bytes:
    """Encode `data` so that the result contains no zero byte (delimiter not appended)."""
    if len(data) < _MAX_BLOCK:
        # Every frame we send: no chunk can reach 254 bytes, so no 0xFF block is possible.
        return b"".join([_CODE[len(chunk) + 1] + chunk for chunk in data.split(b"\x00")])
    out = bytearray()
    for chunk in data.split(b"\x00"):
        # A chunk longer than 254 bytes is split by 0xFF codes, which imply no zero.
        while len(chunk) >= _MAX_BLOCK:
            out.append(0xFF)
            out += chunk[:_MAX_BLOCK]
            chunk = chunk[_MAX_BLOCK:]
        out.append(len(chunk) + 1)
        out += chunk
    return bytes(out)


def decode(enc: bytes | bytearray) -> bytes:
    """Decode one COBS block sequence (no delimiter); raise CobsError when malformed."""
    n = len(enc)
    if n == 0:
        raise CobsError("empty frame")
    out = bytearray(enc[1:])
    # The output is the input shifted left by one, with each code byte after the first
    # replaced by the zero it stands for (none after a 0xFF code, none at the very end).
    pos = enc[0]
    prev = pos
    while pos < n:
        code = enc[pos]
        if code == 0:
            raise CobsError("zero byte inside frame")
        if prev == 0xFF:
            # A 0xFF block implies no zero, so the bytes shift: take the general path.
            return _decode_slow(enc)
        out[pos - 1] = 0
        prev = code
        pos += code
    if pos != n:
        raise CobsError("last block runs past the frame end")
    return bytes(out)


def _decode_slow(enc: bytes | bytearray) -> bytes:
    """Block-by-block decode, used when a 0xFF code (a 254-byte run without zeros) appears."""
    out = bytearray()
    i, n = 0, len(enc)
    while i < n:
        code = enc[i]
        if code == 0:
            raise CobsError("zero byte inside frame")
        end = i + code
        if end > n:
            raise CobsError("last block runs past the frame end")
        out += enc[i + 1 : end]
        if code != 0xFF and end < n:
            out.append(0)
        i = end
    return bytes(out)
