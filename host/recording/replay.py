"""Replay: feed recorded samples to a callback (the registration) in recorded order."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from host.recording.reader import Record, RecordingReader
from host.recording.writer import (
    KIND_ENCODER,
    KIND_EVENT,
    KIND_FRAME,
    KIND_HEAD,
    KIND_HEADER,
    KIND_LINK,
    KIND_POSE,
    KIND_RANGE,
)

ReplayCallback = Callable[[Record], Any]
SAMPLE_KINDS = frozenset(
    {KIND_LINK, KIND_ENCODER, KIND_HEAD, KIND_RANGE, KIND_FRAME, KIND_POSE, KIND_EVENT}
)


@dataclass
class ReplayStats:
    """What a replay saw and what the callback returned."""

    records: int = 0
    by_kind: Counter[str] = field(default_factory=Counter)
    results: list[Any] = field(default_factory=list)
    truncated_bytes: int = 0
    corrupt_files: int = 0
    bad_records: int = 0
    out_of_order: int = 0  # records whose time went backwards within a file
    files_read: int = 0
    skipped: list[tuple[str, str]] = field(default_factory=list)  # (file, why) not read


def replay(
    paths: Iterable[str | Path],
    callback: ReplayCallback,
    kinds: Iterable[str] = SAMPLE_KINDS,
    keep_results: bool = True,
) -> ReplayStats:
    """Call `callback` on every record of the chosen kinds, in file order; deterministic."""
    wanted = frozenset(kinds)
    reader = RecordingReader(paths)
    stats = ReplayStats()
    last: dict[str, int] = {}
    for record in reader:
        if record.kind not in wanted:
            continue
        if record.kind != KIND_HEADER and record.t_ns < last.get(record.file, record.t_ns):
            stats.out_of_order += 1
        last[record.file] = record.t_ns
        stats.records += 1
        stats.by_kind[record.kind] += 1
        result = callback(record)
        if keep_results and result is not None:
            stats.results.append(result)
    stats.truncated_bytes = reader.truncated_bytes
    stats.corrupt_files = reader.corrupt_files
    stats.bad_records = reader.bad_records
    stats.files_read = reader.files_read
    stats.skipped = list(reader.skipped)
    return stats
