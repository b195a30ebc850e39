"""Codec throughput: ENCODER_SAMPLE frames encoded and decoded, beside pymavlink's ATTITUDE.

Run: python benchmarks/bench_codec.py [--messages N] [--repeats R] [--chunk BYTES]
Prints `metric: value` lines; rates are messages per second, best of R repeats, one core.
ATTITUDE (28-byte payload, 40-byte MAVLink 2 frame) is in the same size class as
ENCODER_SAMPLE (17-byte payload, about 26 bytes on the wire).
"""

from __future__ import annotations

import argparse
import random
import time
from collections.abc import Callable

from protocol import FrameDecoder, encode_frame
from protocol.messages import EncoderSample

DEFAULT_MESSAGES = 100_000
DEFAULT_REPEATS = 5
DEFAULT_CHUNK_BYTES = 4096  # a generous serial read; the decoder sees many frames per feed


def _samples(n: int, seed: int = 1) -> list[EncoderSample]:
    """Telemetry with realistic, varied values (so COBS sees a mix of zero runs)."""
    rng = random.Random(seed)
    out = []
    for i in range(n):
        count = rng.randrange(-4_000_000, 4_000_000)
        out.append(
            EncoderSample(
                i * 1000 & 0xFFFF_FFFF, count, count * 4, rng.randrange(-5000, 5000), i & 0x1F
            )
        )
    return out


Workloads = dict[str, Callable[[], int]]


def _chunks(data: bytes, size: int) -> list[bytes]:
    """The stream cut into reads of `size` bytes, cut mid-frame as a UART read would be."""
    return [data[i : i + size] for i in range(0, len(data), size)]


def _decode_workloads(
    frames: list[bytes], chunk: int, decode: Callable[[list[bytes]], int]
) -> Workloads:
    """Decoding a chunked stream, and one frame per call (what datagram transports do)."""
    pieces = _chunks(b"".join(frames), chunk)
    return {"decode_stream": lambda: decode(pieces), "decode_per_frame": lambda: decode(frames)}


def orbitar_workloads(n: int, chunk: int) -> tuple[Workloads, float]:
    """Our codec's workloads over n ENCODER_SAMPLE frames, and the wire bytes per frame."""
    msgs = _samples(n)

    def decode(pieces: list[bytes]) -> int:
        dec = FrameDecoder()
        return sum(len(dec.feed(p)) for p in pieces)

    frames = [encode_frame(m, i & 0xFFFF) for i, m in enumerate(msgs)]
    work = _decode_workloads(frames, chunk, decode)
    work["encode"] = lambda: len([encode_frame(m, i & 0xFFFF) for i, m in enumerate(msgs)])
    return work, sum(map(len, frames)) / n


def pymavlink_workloads(n: int, chunk: int) -> tuple[Workloads, float]:
    """pymavlink's (pure Python) MAVLink 2 ATTITUDE workloads, and its wire bytes per frame."""
    from pymavlink.dialects.v20 import common as mavlink2

    rng = random.Random(1)
    values = [tuple(rng.uniform(-3.0, 3.0) for _ in range(6)) for _ in range(n)]
    sender = mavlink2.MAVLink(None)

    def encode_all() -> list[bytes]:
        return [mavlink2.MAVLink_attitude_message(i, *v).pack(sender) for i, v in enumerate(values)]

    def decode(pieces: list[bytes]) -> int:
        parser = mavlink2.MAVLink(None)
        return sum(len(parser.parse_buffer(p) or ()) for p in pieces)

    frames = encode_all()
    work = _decode_workloads(frames, chunk, decode)
    work["encode"] = lambda: len(encode_all())
    return work, sum(map(len, frames)) / n


def best_rates(n: int, repeats: int, workloads: Workloads) -> dict[str, float]:
    """Messages/s of each workload's fastest run; rounds interleave so load hits all alike."""
    best = dict.fromkeys(workloads, 0.0)
    for _ in range(repeats):
        for name, work in workloads.items():
            start = time.perf_counter()
            done = work()
            elapsed = time.perf_counter() - start
            if done != n:
                raise RuntimeError(f"{name} handled {done} of {n} messages")
            best[name] = max(best[name], n / elapsed)
    return best


def main() -> None:
    """Run both codecs and print the figures side by side."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--messages", type=int, default=DEFAULT_MESSAGES)
    ap.add_argument("--repeats", type=int, default=DEFAULT_REPEATS)
    ap.add_argument("--chunk", type=int, default=DEFAULT_CHUNK_BYTES)
    args = ap.parse_args()
    ours, our_bytes = orbitar_workloads(args.messages, args.chunk)
    theirs, their_bytes = pymavlink_workloads(args.messages, args.chunk)
    both = {f"orbitar_{k}": w for k, w in ours.items()}
    both.update({f"pymavlink_{k}": w for k, w in theirs.items()})
    rates = best_rates(args.messages, args.repeats, both)
    print(f"messages: {args.messages}")
    print(f"stream_chunk_bytes: {args.chunk}")
    print(f"orbitar_encoder_sample_wire_bytes: {our_bytes:.1f}")
    print(f"pymavlink_attitude_wire_bytes: {their_bytes:.1f}")
    for key in ("encode", "decode_stream", "decode_per_frame"):
        print(f"orbitar_{key}_msg_per_s: {rates['orbitar_' + key]:.0f}")
        print(f"pymavlink_{key}_msg_per_s: {rates['pymavlink_' + key]:.0f}")
    for key in ("encode", "decode_per_frame", "decode_stream"):
        ratio = rates["orbitar_" + key] / rates["pymavlink_" + key]
        label = "decode" if key == "decode_stream" else key
        print(f"{label}_ratio_vs_pymavlink: {ratio:.2f}")


if __name__ == "__main__":
    main()
