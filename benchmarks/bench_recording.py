"""Recording costs: what `write()` costs its caller (the event loop), healthy and on a hung disk.

Peer: packing the same record and appending it to a file inline, which is what the writer did
on the loop before it had a thread. Also the writer thread's throughput and its JPEG cost.

    .venv/bin/python benchmarks/bench_recording.py
"""

from __future__ import annotations

import argparse
import io
import tempfile
import threading
import time
from pathlib import Path

import msgpack
import numpy as np

from host.recording.files import FileSystem
from host.recording.writer import RecordingWriter, _jpeg

LINK_RECORD = {"dir": "rx", "bytes": bytes(range(26)) + b"\x00"}


class Hung(FileSystem):
    """A disk whose every write hangs until released."""

    def __init__(self) -> None:
        self.release = threading.Event()

    def write(self, fd: int, data: memoryview) -> int:
        self.release.wait()
        return super().write(fd, data)


def _write_call_ns(writer: RecordingWriter, n: int) -> float:
    """Mean ns per write() call seen by the caller."""
    t0 = time.perf_counter_ns()
    for i in range(n):
        writer.write("link", i, LINK_RECORD)
    return (time.perf_counter_ns() - t0) / n


def _inline_ns(directory: Path, n: int) -> float:
    """Mean ns per record packed and appended on the caller's thread (the old way)."""
    packer = msgpack.Packer(use_bin_type=True)
    with open(directory / "inline.bin", "wb") as f:
        t0 = time.perf_counter_ns()
        for i in range(n):
            f.write(packer.pack({"k": "link", "t": i, "d": LINK_RECORD}))
        f.flush()
        return (time.perf_counter_ns() - t0) / n


def _throughput(directory: Path, n: int) -> float:
    """Records per second through the thread to rotating files, waiting for room."""
    writer = RecordingWriter(directory / "t", rotate_mb=8, keep_files=100, drop_when_full=False)
    writer.open()
    t0 = time.perf_counter()
    for i in range(n):
        writer.write("link", i, LINK_RECORD)
    writer.close(timeout_s=60.0)
    return writer.records / (time.perf_counter() - t0)


def main() -> None:
    """Print the metrics."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--records", type=int, default=40_000)
    args = parser.parse_args()
    n = args.records
    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        healthy = RecordingWriter(directory / "h")
        healthy.open()
        healthy_ns = _write_call_ns(healthy, n)
        healthy.close(timeout_s=30.0)
        hung_fs = Hung()
        hung = RecordingWriter(directory / "s", fs=hung_fs, queue_records=n // 4)
        hung.open()
        hung_ns = _write_call_ns(hung, n)
        dropped = hung.dropped
        hung_fs.release.set()
        hung.close(timeout_s=30.0)
        inline_ns = _inline_ns(directory, n)
        rate = _throughput(directory, n)
    image = np.random.default_rng(1).integers(0, 255, (720, 1280, 3), dtype=np.uint8)
    image[:, :640] //= 4  # some structure, as a real frame has
    t0 = time.perf_counter()
    jpeg = _jpeg(image)
    for _ in range(9):
        _jpeg(image)
    jpeg_ms = (time.perf_counter() - t0) * 100
    buf = io.BytesIO()
    t0 = time.perf_counter()
    for _ in range(10):
        buf.write(image.tobytes())
    copy_ms = (time.perf_counter() - t0) * 100
    print(f"recording_write_call_ns: {healthy_ns:.0f}")
    print(f"recording_write_call_ns_disk_hung: {hung_ns:.0f}")
    print(f"recording_records_dropped_disk_hung: {dropped}")
    print(f"peer_inline_pack_and_append_ns: {inline_ns:.0f}")
    print(f"recording_thread_records_per_s: {rate:.0f}")
    print(f"recording_jpeg_encode_ms_1280x720: {jpeg_ms:.1f}")
    print(f"recording_jpeg_bytes_1280x720: {len(jpeg or b'')}")
    print(f"peer_raw_frame_copy_ms_1280x720: {copy_ms:.2f}")


if __name__ == "__main__":
    main()
