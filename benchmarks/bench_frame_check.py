"""Damaged frames that pass the frame check: version 1's CRC-16/IBM-3740 beside version 2's GENIBUS.

Run: python benchmarks/bench_frame_check.py [--buffers N] [--seed S]
Each buffer is one vector frame with one random edit of its encoded bytes (a bit flip, a byte
overwritten, bytes inserted, deleted or duplicated, a 0x01 appended or removed before the
delimiter: the issue's case). A buffer "passes" when it still COBS-decodes to a frame of legal
length that differs from the original and the check accepts it. Both checks see the very same
damaged bytes; the frames are re-checked with each CRC, so only the check differs.
Prints `metric: value` lines.
"""

from __future__ import annotations

import argparse
import json
import random
from pathlib import Path

from protocol import cobs
from protocol.crc import FRAME_RESIDUE, crc16, frame_crc

VECTORS = Path(__file__).resolve().parents[1] / "protocol" / "vectors.json"
MIN_RAW = 7


def _frames() -> list[bytes]:
    """Every vector's raw frame without its CRC."""
    doc = json.loads(VECTORS.read_text())
    return [bytes.fromhex(v["raw_hex"])[:-2] for v in doc["vectors"]]


def _mutate(rng: random.Random, enc: bytearray) -> None:
    """One random edit of COBS bytes (never a 0x00: the delimiter stays where it is)."""
    op = rng.randrange(7)
    pos = rng.randrange(len(enc))
    if op == 0:
        enc[pos] = enc[pos] ^ (1 << rng.randrange(8)) or 1
    elif op == 1:
        enc[pos] = rng.randrange(1, 256)
    elif op == 2:
        enc[pos:pos] = bytes(rng.randrange(1, 256) for _ in range(rng.randint(1, 4)))
    elif op == 3:
        del enc[pos : pos + rng.randint(1, 4)]
    elif op == 4:
        enc[pos:pos] = enc[pos : pos + rng.randint(1, 8)]
    elif op == 5:
        enc.append(0x01)  # a decoded zero byte appended
    elif enc[-1] == 0x01:
        del enc[-1]  # a trailing decoded zero removed (when the frame ends in one)


def _passes(enc: bytes, original: bytes, residue: int) -> bool:
    """Damaged, still decodable, and accepted by the check with this residue."""
    try:
        raw = cobs.decode(enc)
    except cobs.CobsError:
        return False
    return len(raw) >= MIN_RAW and raw != original and crc16(raw) == residue


def main() -> None:
    """Run and print the figures."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--buffers", type=int, default=200_000)
    ap.add_argument("--seed", type=int, default=13)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    bodies = _frames()
    passed = {"v1_ibm3740": 0, "v2_genibus": 0}
    for _ in range(args.buffers):
        body = rng.choice(bodies)  # the same header and payload under both checks
        state = rng.getstate()
        for name, crc, residue in (
            ("v1_ibm3740", crc16(body), 0),
            ("v2_genibus", frame_crc(body), FRAME_RESIDUE),
        ):
            original = body + crc.to_bytes(2, "big")
            enc = bytearray(cobs.encode(original))
            rng.setstate(state)  # the same edit for both checks
            _mutate(rng, enc)
            passed[name] += _passes(bytes(enc), original, residue)
    print(f"buffers: {args.buffers}")
    for name, n in passed.items():
        print(f"damaged_frames_accepted_{name}: {n}")


if __name__ == "__main__":
    main()
