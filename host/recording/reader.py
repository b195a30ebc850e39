"""Reading recordings back: records in order, tolerant of a truncated last record."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from host.recording.writer import FORMAT_NAME, FORMAT_VERSION, KIND_HEADER, recording_paths

log = logging.getLogger(__name__)

READ_CHUNK_BYTES = 1 << 16


@dataclass(frozen=True)
class Record:
    """One recorded item."""

    kind: str
    t_ns: int
    data: Any
    file: str
    index: int  # position in its file, the header being 0


class RecordingError(Exception):
    """A file is not a recording this reader understands."""


def recording_files(paths: Iterable[str | Path]) -> list[Path]:
    """Expand directories into their recording files; files are taken as given, in order."""
    out: list[Path] = []
    for path in map(Path, paths):
        out.extend(recording_paths(path) if path.is_dir() else [path])
    return out


class RecordingReader:
    """Iterates the records of one or more files; counts what it had to skip."""

    def __init__(self, paths: Iterable[str | Path]) -> None:
        self.paths = recording_files(paths)
        self.truncated_bytes = 0  # an unfinished last record (the writer was killed)
        self.corrupt_files = 0  # files whose bytes stopped making sense part way
        self.bad_records = 0  # well-formed msgpack that is not a record

    def __iter__(self) -> Iterator[Record]:
        for path in self.paths:
            yield from self._read_file(path)

    def _read_file(self, path: Path) -> Iterator[Record]:
        """Records of one file, header checked first."""
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=64 * 1024 * 1024)
        index, fed, complete = 0, 0, 0
        with open(path, "rb") as f:
            while chunk := f.read(READ_CHUNK_BYTES):
                unpacker.feed(chunk)
                fed += len(chunk)
                try:
                    for obj in unpacker:
                        # tell() also counts a partly parsed container, so note it per object.
                        complete = unpacker.tell()
                        record = self._record(obj, path, index)
                        index += 1
                        if record is not None:
                            yield record
                except (ValueError, msgpack.UnpackException) as exc:
                    self._corrupt(path, exc)
                    return
        self.truncated_bytes += fed - complete

    def _record(self, obj: Any, path: Path, index: int) -> Record | None:
        """A record from a decoded map; None (counted) for anything else."""
        if not isinstance(obj, dict) or not isinstance(obj.get("k"), str):
            self.bad_records += 1
            return None
        if index == 0:
            _check_header(obj, path)
        t_ns = obj.get("t")
        return Record(
            obj["k"], t_ns if isinstance(t_ns, int) else 0, obj.get("d"), str(path), index
        )

    def _corrupt(self, path: Path, exc: Exception) -> None:
        """Stop reading a file whose bytes stopped making sense."""
        self.corrupt_files += 1
        log.warning("recording corrupt, rest skipped", extra={"kv": {"file": path, "error": exc}})


def _check_header(obj: dict[str, Any], path: Path) -> None:
    """The first record must name our format and a version we read."""
    data = obj.get("d")
    if obj["k"] != KIND_HEADER or not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
        raise RecordingError(f"{path}: not an Orbitar recording")
    if data.get("version") != FORMAT_VERSION:
        raise RecordingError(f"{path}: recording version {data.get('version')} not supported")
