"""CRC-16/IBM-3740 (also called CRC-16/CCITT-FALSE): poly 0x1021, init 0xFFFF, no reflection.

Catalogue check value: crc16(b"123456789") == 0x29B1. The stdlib's binascii.crc_hqx computes
this polynomial unreflected at C speed; seeded with 0xFFFF it is exactly this CRC.
"""

from __future__ import annotations

import binascii

CRC_INIT = 0xFFFF
CRC_POLY = 0x1021
CHECK_VALUE = 0x29B1


def crc16(data: bytes, crc: int = CRC_INIT) -> int:
    """CRC-16/IBM-3740 of `data`, optionally continuing from a previous value."""
    return binascii.crc_hqx(data, crc)


def crc16_bitwise(data: bytes) -> int:
    """Bit-at-a-time reference, the way a small C implementation computes it."""
    crc = CRC_INIT
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc
