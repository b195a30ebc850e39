"""Rotating msgpack recording files: one map per record, `{"k": kind, "t": t_ns, "d": data}`.

A file starts with a `header` record naming the format and version. Records are appended through
a buffered file and flushed at least every FLUSH_INTERVAL_S, so a crash loses at most that much
and leaves at worst a truncated last record, which the reader tolerates.
"""

from __future__ import annotations

import logging
import os
import re
import time
from pathlib import Path
from typing import Any, BinaryIO

import msgpack

log = logging.getLogger(__name__)

FORMAT_NAME = "orbitar-recording"
FORMAT_VERSION = 1
SUFFIX = ".orec"
FILE_RE = re.compile(r"^orbitar-(\d{6})" + re.escape(SUFFIX) + "$")
FLUSH_INTERVAL_S = 1.0
BYTES_PER_MB = 1024 * 1024

# Record kinds written by the daemon (readers must skip kinds they do not know).
KIND_HEADER = "header"
KIND_LINK = "link"  # {"dir": "rx"|"tx", "bytes": raw wire bytes}
KIND_ENCODER = "encoder"  # decoded ENCODER_SAMPLE fields + host_t_ns
KIND_HEAD = "head"  # decoded HEAD_SAMPLE fields
KIND_RANGE = "range"  # {"distance_mm", "quality"}: RANGE_SAMPLE, when ranging feeds the pose
KIND_FRAME = "frame"  # {"index", "exposure_ns", "jpeg"?}
KIND_POSE = "pose"  # PoseSample.to_dict()
KIND_EVENT = "event"  # daemon events: link up/down, reload, …


class RecordingWriter:
    """Appends records to `dir/orbitar-NNNNNN.orec`, rotating by size and keeping N files."""

    def __init__(
        self,
        directory: str | Path,
        rotate_mb: float = 64.0,
        keep_files: int = 10,
        include_frames: bool = False,
    ) -> None:
        self.directory = Path(directory)
        self.rotate_bytes = int(rotate_mb * BYTES_PER_MB)
        self.keep_files = keep_files
        self.include_frames = include_frames
        self.records = 0
        self.errors = 0
        self.current: Path | None = None
        self._file: BinaryIO | None = None
        self._size = 0
        self._last_flush = time.monotonic()
        self._packer = msgpack.Packer(use_bin_type=True)

    def open(self) -> None:
        """Create the directory and start a new file."""
        self.directory.mkdir(parents=True, exist_ok=True)
        self._start_file()

    def write(self, kind: str, t_ns: int, data: Any) -> bool:
        """Append one record; False (and counted) if it could not be written."""
        if self._file is None:
            return False
        if kind == KIND_FRAME and not self.include_frames:
            data = _without_jpeg(data)
        try:
            blob = self._packer.pack({"k": kind, "t": t_ns, "d": data})
            self._file.write(blob)
        except (OSError, ValueError, TypeError) as exc:
            self._count_error(exc)
            return False
        self.records += 1
        self._size += len(blob)
        self._maybe_flush_or_rotate()
        return True

    def close(self) -> None:
        """Flush and close the current file."""
        if self._file is not None:
            try:
                self._file.close()
            except OSError as exc:
                self._count_error(exc)
            self._file = None

    def files(self) -> list[Path]:
        """Recording files in the directory, oldest first."""
        return recording_paths(self.directory)

    def _start_file(self) -> None:
        """Open the next numbered file and write its header."""
        number = _file_number(self.files()[-1]) + 1 if self.files() else 1
        self.current = self.directory / f"orbitar-{number:06d}{SUFFIX}"
        self._file = open(self.current, "xb")  # noqa: SIM115 - owned until close()
        self._size = 0
        header = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "unix_time": time.time()}
        self.write(KIND_HEADER, time.monotonic_ns(), header)
        self._prune()

    def _maybe_flush_or_rotate(self) -> None:
        """Rotate above the size limit; flush at least every FLUSH_INTERVAL_S."""
        assert self._file is not None
        if self._size >= self.rotate_bytes:
            self.close()
            try:
                self._start_file()
            except OSError as exc:
                self._count_error(exc)
            return
        now = time.monotonic()
        if now - self._last_flush >= FLUSH_INTERVAL_S:
            self._last_flush = now
            try:
                self._file.flush()
            except OSError as exc:
                self._count_error(exc)

    def _prune(self) -> None:
        """Delete the oldest files beyond keep_files."""
        files = self.files()
        for old in files[: max(0, len(files) - self.keep_files)]:
            try:
                old.unlink()
            except OSError as exc:
                self._count_error(exc)

    def _count_error(self, exc: Exception) -> None:
        """Count a write problem and log the first few."""
        self.errors += 1
        if self.errors <= 3:
            log.error("recording write failed", extra={"kv": {"error": exc}})


def recording_paths(directory: Path) -> list[Path]:
    """`orbitar-NNNNNN.orec` files in a directory, in number order."""
    try:
        names = [n for n in os.listdir(directory) if FILE_RE.match(n)]
    except FileNotFoundError:
        return []
    return [directory / n for n in sorted(names)]


def _file_number(path: Path) -> int:
    """NNNNNN of orbitar-NNNNNN.orec."""
    match = FILE_RE.match(path.name)
    return int(match.group(1)) if match else 0


def _without_jpeg(data: Any) -> Any:
    """A frame record without its image, when frames are not recorded."""
    return {k: v for k, v in data.items() if k != "jpeg"} if isinstance(data, dict) else data
