"""Recording files: round trip, rotation, truncation and corruption tolerance, replay."""

from __future__ import annotations

from pathlib import Path

import msgpack
import pytest

from host.recording import RecordingReader, RecordingWriter, replay
from host.recording.reader import Record, RecordingError


def write_samples(directory: Path, n: int, **kw: object) -> RecordingWriter:
    """A recording of n encoder samples and n frames."""
    writer = RecordingWriter(directory, drop_when_full=False, **kw)  # type: ignore[arg-type]
    writer.open()
    for i in range(n):
        writer.write("encoder", 1_000 * i, {"count": i, "mcu_time_us": 250 * i})
        writer.write("frame", 1_000 * i + 500, {"index": i, "jpeg": b"\xff\xd8" + bytes(100)})
    writer.close()
    return writer


def test_round_trip_in_order(tmp_path: Path) -> None:
    write_samples(tmp_path, 50)
    records = list(RecordingReader([tmp_path]))
    assert records[0].kind == "header"
    encoder = [r.data["count"] for r in records if r.kind == "encoder"]
    assert encoder == list(range(50))
    times = [r.t_ns for r in records[1:]]
    assert times == sorted(times)


def test_frames_lose_their_jpeg_unless_asked(tmp_path: Path) -> None:
    write_samples(tmp_path / "no", 3)
    write_samples(tmp_path / "yes", 3, include_frames=True)
    no = [r.data for r in RecordingReader([tmp_path / "no"]) if r.kind == "frame"]
    yes = [r.data for r in RecordingReader([tmp_path / "yes"]) if r.kind == "frame"]
    assert all("jpeg" not in d for d in no)
    assert all(d["jpeg"].startswith(b"\xff\xd8") for d in yes)


def test_rotation_keeps_the_newest_files(tmp_path: Path) -> None:
    writer = write_samples(tmp_path, 2000, rotate_mb=0.01, keep_files=3)
    files = writer.files()
    assert len(files) == 3
    assert files[-1] == writer.last_file
    counts = [r.data["count"] for r in RecordingReader(files) if r.kind == "encoder"]
    assert counts[-1] == 1999  # the newest survive, in order, with no gap inside the kept files
    assert counts == list(range(counts[0], 2000))
    assert all(sz.stat().st_size < 0.01 * 1024 * 1024 + 300 for sz in files[:-1])


def test_truncated_last_record_is_tolerated(tmp_path: Path) -> None:
    path = write_samples(tmp_path, 10).last_file
    assert path is not None
    data = path.read_bytes()
    path.write_bytes(data[:-7])  # the writer was killed mid-record
    reader = RecordingReader([path])
    encoder = [r for r in reader if r.kind == "encoder"]
    assert len(encoder) == 10  # the cut record was the last frame
    assert reader.truncated_bytes > 0


def test_garbage_in_the_middle_stops_that_file_only(tmp_path: Path) -> None:
    path = write_samples(tmp_path, 10).last_file
    assert path is not None
    data = path.read_bytes()
    path.write_bytes(data[:200] + b"\xc1" * 10 + data[200:])
    reader = RecordingReader([path])
    records = list(reader)
    assert 0 < len(records) < 21
    assert reader.corrupt_files == 1


def test_a_file_that_is_not_a_recording_is_skipped_and_named(tmp_path: Path) -> None:
    path = tmp_path / "x.orec"
    path.write_bytes(msgpack.packb({"k": "encoder", "t": 0, "d": {}}))
    reader = RecordingReader([path])
    assert list(reader) == []
    assert reader.skipped == [(str(path), "not an Orbitar recording")]
    with pytest.raises(RecordingError, match="not an Orbitar recording"):
        list(RecordingReader([path], strict=True))


def test_an_unknown_format_version_is_refused_with_the_versions_read(tmp_path: Path) -> None:
    path = tmp_path / "orbitar-000001.orec"
    header = {"format": "orbitar-recording", "version": 99}
    path.write_bytes(msgpack.packb({"k": "header", "t": 0, "d": header}))
    with pytest.raises(RecordingError) as caught:
        list(RecordingReader([path], strict=True))
    assert "version 99 not supported (this reader reads 1, 2)" in str(caught.value)
    assert "newer orbitar wrote it" in str(caught.value)


def test_version_1_recordings_still_read(tmp_path: Path) -> None:
    path = tmp_path / "orbitar-000001.orec"
    header = {"format": "orbitar-recording", "version": 1, "unix_time": 0.0}
    path.write_bytes(
        msgpack.packb({"k": "header", "t": 0, "d": header})
        + msgpack.packb({"k": "encoder", "t": 5, "d": {"s_mm": 1.0}})
    )
    assert [r.kind for r in RecordingReader([path], strict=True)] == ["header", "encoder"]


def test_replay_is_deterministic_and_filters_kinds(tmp_path: Path) -> None:
    write_samples(tmp_path, 20)

    def registration(record: Record) -> tuple[int, int]:
        return (record.t_ns, record.data["count"] * 2)

    first = replay([tmp_path], registration, kinds=["encoder"])
    second = replay([tmp_path], registration, kinds=["encoder"])
    assert first.results == second.results
    assert first.results[3] == (3000, 6)
    assert first.by_kind == {"encoder": 20}
    assert first.out_of_order == 0


def test_a_rotation_size_below_one_header_still_writes_every_record(tmp_path: Path) -> None:
    writer = write_samples(tmp_path, 5, rotate_mb=1e-6, keep_files=100)  # 1 byte per file
    assert [r.data["count"] for r in RecordingReader([tmp_path]) if r.kind == "encoder"] == [
        0, 1, 2, 3, 4,
    ]  # fmt: skip
    assert len(writer.files()) == 11  # one record per file after its header, and the next file
