"""What a disk does to the recording: full, read-only, gone, stalled; the daemon never notices.

ENOSPC and EROFS come from a `FileSystem` shim: a full tmpfs or a read-only mount would need
mount privileges CI does not have, and chmod does not stop root. The shim writes the bytes the
disk "had room for" for real before failing, so the cut-back is checked on a real file. The
directory blocked by a plain file (ENOTDIR) and the deleted file are real.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from host.recording import RecordingReader
from host.recording import writer as writer_module
from host.recording.files import FileSystem
from host.recording.writer import QUEUE_FRAMES, RecordingState, RecordingWriter

WAIT_S = 10.0


@pytest.fixture(autouse=True)
def quick_retries(monkeypatch: pytest.MonkeyPatch) -> None:
    """Retry after 20 ms instead of 0.5 s, and check for a deleted file every 50 ms."""
    monkeypatch.setattr(writer_module, "RETRY_FIRST_S", 0.02)
    monkeypatch.setattr(writer_module, "RETRY_MAX_S", 0.05)
    monkeypatch.setattr(writer_module, "LINK_CHECK_INTERVAL_S", 0.05)
    monkeypatch.setattr(writer_module, "STALLED_AFTER_S", writer_module.STALLED_AFTER_S)


def wait_until(condition: Callable[[], bool], what: str) -> None:
    """Poll until the writer thread got there (a wait, not a timing claim)."""
    deadline = time.monotonic() + WAIT_S
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"never {what}")
        time.sleep(0.005)


class FullDisk(FileSystem):
    """While `full`: a write stores half its bytes, then fails with ENOSPC, as a disk does."""

    def __init__(self) -> None:
        self.full = False

    def write(self, fd: int, data: memoryview) -> int:
        if self.full:
            os.write(fd, data[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(fd, data)


class ReadOnly(FileSystem):
    """While `read_only`: creating anything fails with EROFS, as on a read-only mount."""

    def __init__(self) -> None:
        self.read_only = True

    def makedirs(self, path: Path) -> None:
        if self.read_only:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        super().makedirs(path)

    def create(self, path: Path) -> int:
        if self.read_only:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return super().create(path)


class Stalled(FileSystem):
    """Every write waits until `release` is set: an NFS server gone, a dying disk."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()  # the writer thread is hanging in a write

    def write(self, fd: int, data: memoryview) -> int:
        self.entered.set()
        self.release.wait()
        return super().write(fd, data)


def hang(writer: RecordingWriter, fs: Stalled) -> None:
    """Start the writer and wait until its thread hangs in its first write (the header)."""
    writer.open()
    writer.write("event", 0, {"start": True})
    assert fs.entered.wait(WAIT_S)


def send(writer: RecordingWriter, first: int, n: int) -> None:
    """Encoder records numbered first … first + n - 1."""
    for i in range(first, first + n):
        writer.write("encoder", i, {"count": i})


def keep_sending(writer: RecordingWriter, state: RecordingState, sent: list[int]) -> bool:
    """One more record (as the link keeps producing them); True once in `state`."""
    n = 5000 + len(sent)
    sent.append(n)
    writer.write("encoder", n, {"count": n})
    return writer.state is state


def counts(directory: Path) -> list[int]:
    """The encoder record numbers that reached the files."""
    return [r.data["count"] for r in RecordingReader([directory]) if r.kind == "encoder"]


def test_a_full_disk_is_a_state_with_a_cut_back_file_then_resumes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    fs = FullDisk()
    writer = RecordingWriter(tmp_path, fs=fs)
    writer.open()
    send(writer, 0, 100)
    wait_until(lambda: writer.records == 100, "wrote the first 100")
    fs.full = True
    with caplog.at_level(logging.WARNING, logger="host.recording.writer"):
        for batch in range(20):  # a second of records into a full disk
            send(writer, 100 + 10 * batch, 10)
            time.sleep(0.01)
        wait_until(lambda: writer.state is RecordingState.FAILING, "saw the disk full")
        shown = writer.status()
        assert shown["state"] == "failing"
        assert "ENOSPC" in shown["last_error"]
        assert shown["file"] is not None
        assert Path(shown["file"]).exists()
        fs.full = False  # space freed: the next write that is due goes through
        extra: list[int] = []
        wait_until(lambda: keep_sending(writer, RecordingState.RECORDING, extra), "resumed")
        send(writer, 1000, 100)
        assert writer.close()
    got = counts(tmp_path)
    assert got[:100] == list(range(100))
    assert got[-100:] == list(range(1000, 1100))  # recording resumed on its own
    assert writer.records + writer.dropped == 400 + len(extra)  # every record written or counted
    assert writer.dropped > 0
    reader = RecordingReader([tmp_path])
    list(reader)
    assert reader.truncated_bytes == 0
    assert reader.corrupt_files == 0
    failing = [r for r in caplog.records if r.getMessage() == "recording failing"]
    assert len(failing) == 1  # logged when it started, not per record
    assert any(r.getMessage() == "recording resumed" for r in caplog.records)


def test_a_read_only_directory_is_retried_until_it_is_writable(tmp_path: Path) -> None:
    fs = ReadOnly()
    writer = RecordingWriter(tmp_path / "rec", fs=fs)
    writer.open()
    send(writer, 0, 10)
    wait_until(lambda: writer.errors >= 3, "retried a few times")
    shown = writer.status()
    assert shown["state"] == "retrying"
    assert "EROFS" in shown["last_error"]
    assert shown["file"] is None  # nothing is named that does not exist
    assert shown["retry_in_s"] is not None
    fs.read_only = False  # remounted read-write
    wait_until(lambda: writer.state is RecordingState.RECORDING, "recovered")
    send(writer, 10, 10)
    shown = writer.status()
    assert Path(shown["file"]).exists()
    assert writer.close()
    assert counts(tmp_path / "rec") == list(range(10, 20))
    assert writer.dropped == 10


def test_a_directory_blocked_by_a_file_recovers_once_it_is_removed(tmp_path: Path) -> None:
    blocker = tmp_path / "disk"
    blocker.write_text("not a directory")
    writer = RecordingWriter(blocker / "rec")
    writer.open()
    wait_until(lambda: writer.errors >= 2, "tried to open")
    assert writer.status()["state"] == "retrying"
    assert "ENOTDIR" in writer.status()["last_error"] or "EEXIST" in writer.status()["last_error"]
    blocker.unlink()
    wait_until(lambda: writer.state is RecordingState.RECORDING, "recovered")
    send(writer, 0, 5)
    assert writer.close()
    assert counts(blocker / "rec") == list(range(5))


def test_a_deleted_file_is_replaced_not_reported(tmp_path: Path) -> None:
    writer = RecordingWriter(tmp_path)
    writer.open()
    wait_until(lambda: writer.current is not None, "opened")
    first = writer.current
    assert first is not None
    first.unlink()  # an operator cleaning up, a tmp cleaner
    send(writer, 0, 1)
    wait_until(lambda: writer.current not in (None, first), "reopened")
    send(writer, 1, 5)
    assert writer.status()["file"] == str(writer.current)
    assert writer.close()
    assert counts(tmp_path)[-5:] == list(range(1, 6))


def test_a_stalled_disk_never_blocks_the_caller(tmp_path: Path) -> None:
    fs = Stalled()
    writer = RecordingWriter(tmp_path, fs=fs, queue_records=100)
    hang(writer, fs)
    try:
        # The writer thread now hangs in its first write. If write() waited for the disk, this
        # loop would hang with it: it returns, keeping 100 records and counting the rest.
        accepted = sum(writer.write("encoder", i, {"count": i}) for i in range(1000))
        assert accepted == 100
        assert writer.status()["dropped_queue_full"] == 900
        assert writer.status()["queued"] == 100
        writer_module.STALLED_AFTER_S = 0.0  # (restored by monkeypatch) the hang shows at once
        assert writer.status()["state"] == "failing"
        assert "disk not answering" in writer.status()["last_error"]
    finally:
        fs.release.set()
    assert writer.close()
    assert counts(tmp_path) == list(range(100))


def test_frames_wait_for_encoding_in_a_queue_of_their_own_size(tmp_path: Path) -> None:
    fs = Stalled()
    writer = RecordingWriter(tmp_path, fs=fs, include_frames=True)
    hang(writer, fs)
    image = np.zeros((48, 64, 3), np.uint8)
    try:
        taken = [writer.write("frame", i, {"index": i, "image": image}) for i in range(20)]
        samples = [writer.write("encoder", i, {"count": i}) for i in range(20)]
    finally:
        fs.release.set()
    assert sum(taken) == QUEUE_FRAMES
    assert all(samples)
    # what is under test is the queues; the queued frames are encoded before close can finish,
    # which on 2 busy cores can outlast the SIGTERM share close has by default
    assert writer.close(timeout_s=WAIT_S)
    frames = [r.data for r in RecordingReader([tmp_path]) if r.kind == "frame"]
    assert [f["index"] for f in frames] == list(range(QUEUE_FRAMES))
    assert all(f["jpeg"].startswith(b"\xff\xd8") for f in frames)


async def test_a_stalled_disk_does_not_stall_the_event_loop(tmp_path: Path) -> None:
    fs = Stalled()
    # Should write() ever wait for the disk, this releases it, and the check below fails.
    rescue = threading.Timer(WAIT_S, fs.release.set)
    rescue.start()
    writer = RecordingWriter(tmp_path, fs=fs, queue_records=1000)
    hang(writer, fs)
    ticks = 0

    async def heartbeat() -> None:
        nonlocal ticks
        for _ in range(50):
            await asyncio.sleep(0.001)
            ticks += 1

    async def link() -> None:
        for i in range(5000):  # a link's worth of records while the disk hangs
            writer.write("link", i, {"dir": "rx", "bytes": b"\x01\x02\x03\x00"})
            if i % 100 == 0:
                await asyncio.sleep(0)

    try:
        await asyncio.gather(heartbeat(), link())
        assert not fs.release.is_set()  # all of it ran while the disk was still stalled
    finally:
        rescue.cancel()
        fs.release.set()
    assert ticks == 50
    assert writer.status()["dropped_queue_full"] == 4000  # kept what the queue holds
    assert writer.close()
    assert sum(r.kind == "link" for r in RecordingReader([tmp_path])) == 1000
