"""Reading recordings back: records in order, tolerant of a truncated last record.

A file that is not a recording this reader understands (another format, a newer version, an
empty file the disk filled up before its header) is skipped and named in `skipped` with why;
only a caller that needs every file (`strict=True`) gets a `RecordingError` instead.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from host.recording.files import FILE_RE, recording_paths
from host.recording.writer import FORMAT_NAME, FORMAT_VERSION, KIND_HEADER, READABLE_VERSIONS

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


def recording_files(
    paths: Iterable[str | Path], skipped: list[tuple[str, str]] | None = None
) -> list[Path]:
    """Expand directories into their recording files; files are taken as given, in order.

    Other entries of a directory are noted in `skipped` (name, why) when a list is given.
    """
    out: list[Path] = []
    for path in map(Path, paths):
        if not path.is_dir():
            out.append(path)
            continue
        out.extend(recording_paths(path))
        if skipped is not None:
            for other in sorted(path.iterdir()):
                if not FILE_RE.match(other.name):
                    why = "a directory" if other.is_dir() else "not named orbitar-NNNNNN.orec"
                    skipped.append((str(other), why))
    return out


class RecordingReader:
    """Iterates the records of one or more files; counts what it had to skip."""

    def __init__(self, paths: Iterable[str | Path], strict: bool = False) -> None:
        self.skipped: list[tuple[str, str]] = []  # (file, why) for every file not read
        self.paths = recording_files(paths, self.skipped)
        self.strict = strict
        self.truncated_bytes = 0  # an unfinished last record (the writer was killed)
        self.corrupt_files = 0  # files whose bytes stopped making sense part way
        self.bad_records = 0  # well-formed msgpack that is not a record
        self.files_read = 0

    def __iter__(self) -> Iterator[Record]:
        for path in self.paths:
            try:
                yield from self._read_file(path)
            except (RecordingError, OSError) as exc:
                if self.strict:
                    raise RecordingError(str(exc)) from exc
                why = str(exc).removeprefix(f"{path}: ")
                self.skipped.append((str(path), why))
                log.warning("recording skipped", extra={"kv": {"file": path, "why": why}})

    def _read_file(self, path: Path) -> Iterator[Record]:
        """Records of one file, header checked first."""
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=64 * 1024 * 1024)
        index, fed, complete = 0, 0, 0
        with open(path, "rb") as f:
            if f.read(1) == b"":
                raise RecordingError(f"{path}: empty (no header was written)")
            f.seek(0)
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
                    if index == 0:
                        raise RecordingError(f"{path}: not an Orbitar recording") from exc
                    self._corrupt(path, exc)
                    return
        if index == 0:
            raise RecordingError(f"{path}: not an Orbitar recording (no whole header)")
        self.files_read += 1
        self.truncated_bytes += fed - complete

    def _record(self, obj: Any, path: Path, index: int) -> Record | None:
        """A record from a decoded map; None (counted) for anything else."""
        if index == 0:
            if not isinstance(obj, dict):
                raise RecordingError(f"{path}: not an Orbitar recording")
            _check_header(obj, path)
        elif not isinstance(obj, dict) or not isinstance(obj.get("k"), str):
            self.bad_records += 1
            return None
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
    is_header = obj.get("k") == KIND_HEADER and isinstance(data, dict)
    if not is_header or not isinstance(data, dict) or data.get("format") != FORMAT_NAME:
        raise RecordingError(f"{path}: not an Orbitar recording")
    version = data.get("version")
    if version not in READABLE_VERSIONS:
        newer = isinstance(version, int) and version > FORMAT_VERSION
        hint = "; a newer orbitar wrote it: upgrade to read it" if newer else ""
        readable = ", ".join(map(str, READABLE_VERSIONS))
        raise RecordingError(
            f"{path}: recording format version {version!r} not supported "
            f"(this reader reads {readable}){hint}"
        )
