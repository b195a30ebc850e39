"""The frame check, CRC-16/GENIBUS, built on the CRC-16/IBM-3740 register.

`crc16` is CRC-16/IBM-3740 (CRC-16/CCITT-FALSE): poly 0x1021, init 0xFFFF, no reflection, no
final XOR; check value 0x29B1. The stdlib's binascii.crc_hqx computes it at C speed. It checked
frames up to protocol version 1 and still checks the parameter record in flash.

From protocol version 2 a frame carries `frame_crc`, CRC-16/GENIBUS: the same register with a
final XOR of 0xFFFF (check value 0xD64E). Without the final XOR a good frame leaves the register
at zero and zero bytes appended to it (or a trailing zero removed) leave it at zero too, so they
passed; with it a good frame leaves the constant FRAME_RESIDUE, which an appended zero changes.
"""

from __future__ import annotations

import binascii

CRC_INIT = 0xFFFF
CRC_POLY = 0x1021
CHECK_VALUE = 0x29B1
FRAME_XOROUT = 0xFFFF
FRAME_CHECK_VALUE = 0xD64E  # frame_crc(b"123456789")
FRAME_RESIDUE = 0x1D0F  # crc16 over a good frame, its frame_crc included


def crc16(data: bytes, crc: int = CRC_INIT) -> int:
    """CRC-16/IBM-3740 of `data`, optionally continuing from a previous value."""
    return binascii.crc_hqx(data, crc)


def frame_crc(data: bytes) -> int:
    """CRC-16/GENIBUS of a frame's header and payload (protocol version 2 on)."""
    return binascii.crc_hqx(data, CRC_INIT) ^ FRAME_XOROUT


def frame_ok(raw: bytes) -> bool:
    """Whether a raw frame (header, payload, frame_crc big-endian) passes the check."""
    return binascii.crc_hqx(raw, CRC_INIT) == FRAME_RESIDUE


def crc16_bitwise(data: bytes) -> int:
    """Bit-at-a-time reference, the way a small C implementation computes it."""
    crc = CRC_INIT
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc
