"""Parameters in RAM and their CRC-protected record in the flash sector.

Record layout (little-endian): magic u32 'ORBP', layout version u16, count u16, then `count`
entries of (param id u16, value i32), then CRC-16/IBM-3740 of everything before it, big-endian.
An erased sector (empty or all 0xFF) is a fresh board: defaults, no fault. Anything else that
does not check out is corruption: defaults and a FLASH fault, so the host is told.
"""

from __future__ import annotations

import enum
import struct

from protocol.crc import crc16
from protocol.params import PARAMS, PARAMS_BY_ID, ParamId

RECORD_MAGIC = 0x5042_524F  # "ORBP" read as little-endian bytes
RECORD_VERSION = 1
_HEAD = struct.Struct("<IHH")
_ENTRY = struct.Struct("<Hi")
ERASED_BYTE = 0xFF


class LoadResult(enum.Enum):
    """What booting found in the parameter sector."""

    LOADED = "loaded"
    ERASED = "erased"  # fresh board: defaults, not a fault
    CORRUPT = "corrupt"  # defaults loaded and the FLASH fault latched


class ParamStore:
    """The parameter table in RAM, indexed by id, with flash load and persist."""

    __slots__ = ("values",)

    def __init__(self) -> None:
        self.values: dict[int, int] = {int(p.id): p.default for p in PARAMS}

    def get(self, pid: ParamId) -> int:
        """A parameter's value in force."""
        return self.values[int(pid)]

    def set(self, pid: int, value: int) -> bool:
        """Set a known parameter within its range; False (nothing changed) otherwise."""
        spec = PARAMS_BY_ID.get(pid)
        if spec is None or not spec.lo <= value <= spec.hi:
            return False
        self.values[pid] = value
        return True

    def reset_defaults(self) -> None:
        """Every parameter back to its default."""
        for p in PARAMS:
            self.values[int(p.id)] = p.default

    def encode(self) -> bytes:
        """The flash record of the values in force."""
        body = _HEAD.pack(RECORD_MAGIC, RECORD_VERSION, len(self.values))
        body += b"".join(_ENTRY.pack(pid, v) for pid, v in sorted(self.values.items()))
        return body + crc16(body).to_bytes(2, "big")

    def load(self, record: bytes) -> LoadResult:
        """Load a flash record; on any fault keep the defaults."""
        self.reset_defaults()
        if not record or all(b == ERASED_BYTE for b in record):
            return LoadResult.ERASED
        parsed = _parse(record)
        if parsed is None:
            return LoadResult.CORRUPT
        staged = ParamStore()
        for pid, value in parsed:
            if not staged.set(pid, value):
                return LoadResult.CORRUPT
        self.values.update(staged.values)
        return LoadResult.LOADED


def _parse(record: bytes) -> list[tuple[int, int]] | None:
    """Entries of a record whose magic, version, length and CRC check out; else None."""
    if len(record) < _HEAD.size + 2 or crc16(record) != 0:
        return None
    magic, version, count = _HEAD.unpack_from(record)
    if magic != RECORD_MAGIC or version != RECORD_VERSION:
        return None
    if len(record) != _HEAD.size + count * _ENTRY.size + 2:
        return None
    return [_ENTRY.unpack_from(record, _HEAD.size + i * _ENTRY.size) for i in range(count)]
