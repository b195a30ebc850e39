"""`orbitar replay` re-runs the registration on a recording, the same way every time."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from host.config import Config
from host.recording import RecordingWriter
from host.service.replay_registration import run
from host.service.wiring import build_rig

MS = 1_000_000
PAN, TILT = 0.3, -0.2


def _record(directory: Path) -> None:
    """100 ms of 1 kHz encoder samples at 0.1 m/s, a fixed head, frames and one late pose."""
    writer = RecordingWriter(directory)
    writer.open()
    for i in range(100):
        writer.write("encoder", i * MS, {"s_mm": 500.0 + 0.1 * i, "v_mm_s": 100.0, "inputs": 0x10})
        writer.write("head", i * MS, {"pan_rad": PAN, "tilt_rad": TILT})
        if i % 10 == 5:
            writer.write("frame", i * MS + MS // 2, {"index": i, "exposure_ns": i * MS + MS // 2})
    writer.write("pose", 5_000 * MS, {"note": "far past the last sample"})
    writer.close()


def _replay(rec: Path, out: Path) -> list[dict[str, Any]]:
    args = argparse.Namespace(files=[str(rec)], config=None, out=str(out))
    assert run(args) == 0
    return [json.loads(line) for line in out.read_text().splitlines()]


def test_replay_re_registers_every_frame_and_is_deterministic(tmp_path: Path) -> None:
    _record(tmp_path / "rec")
    first = _replay(tmp_path / "rec", tmp_path / "a.jsonl")
    second = _replay(tmp_path / "rec", tmp_path / "b.jsonl")
    assert first == second
    frames = [p for p in first if p["kind"] == "frame"]
    assert len(frames) == 10
    rig = build_rig(Config())
    for pose in frames:
        t_ms = int(pose["t_ns"]) / MS
        s = 500.0 + 0.1 * t_ms
        assert pose["status"] == "ok"
        assert pose["s_mm"] == pytest.approx(s, abs=1e-6)
        np.testing.assert_allclose(pose["T_w_c"], rig.T_w_c(s, PAN, TILT), atol=1e-5)
    assert first[-1]["kind"] == "pose"
    assert first[-1]["status"] == "stale"  # never guessed past the horizon


def test_replay_reports_a_broken_recording(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.orec"
    bad.write_bytes(msgpack.packb({"k": "oops"}))
    assert run(argparse.Namespace(files=[str(bad)], config=None, out=None)) == 1
    assert "orbitar replay" in capsys.readouterr().err


def test_replay_applies_recorded_rangefinder_fixes(tmp_path: Path) -> None:
    """A stretched chain read against a surveyed wall: the replay corrects as the daemon did."""
    rig = tmp_path / "rig.toml"
    rig.write_text(
        "[track.home]\nvalue_mm = 100.0\n[[hall.surfaces]]\nname = 'east wall'\n"
        "point_mm = [6000, 0, 0]\nnormal = [-1, 0, 0]\n"
    )
    config = tmp_path / "orbitar.toml"
    config.write_text(f'[rig]\npath = "{rig}"\n')
    stretch = 1.005
    writer = RecordingWriter(tmp_path / "rec")
    writer.open()
    for i in range(2000):  # 2 s at 0.5 m/s along the first straight, looking ahead
        true_s = 100.0 + 0.5 * i * stretch
        writer.write("encoder", i * MS, {"s_mm": 0.5 * i, "v_mm_s": 500.0, "inputs": 0x10})
        if i % 10 == 0:
            writer.write("head", i * MS, {"pan_rad": 0.0, "tilt_rad": np.pi / 2})
            writer.write("range", i * MS + 1, {"distance_mm": 8000.0 - true_s, "quality": 200})
        if i % 33 == 20:
            writer.write("frame", i * MS + 2, {"index": i, "exposure_ns": i * MS + 2})
    writer.close()
    args = argparse.Namespace(files=[str(tmp_path / "rec")], config=str(config), out=None)
    out = tmp_path / "poses.jsonl"
    args.out = str(out)
    assert run(args) == 0
    frames = [json.loads(line) for line in out.read_text().splitlines()]
    late = [f for f in frames if f["t_ns"] > 1000 * MS]
    assert len(late) == 30
    for f in late:
        true_s = 100.0 + 0.5 * (f["t_ns"] // MS) * stretch
        assert f["s_mm"] == pytest.approx(true_s, abs=0.1)  # encoder-only would be 2.5-5 mm off


def test_malformed_sample_records_are_counted_and_skipped(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    writer = RecordingWriter(tmp_path / "rec")
    writer.open()
    writer.write("encoder", 1 * MS, {"v_mm_s": 0.0})  # no s_mm
    writer.write("range", 2 * MS, {"distance_mm": "far"})
    writer.write("head", 3 * MS, {"pan_rad": 0.1, "tilt_rad": 0.2})
    writer.close()
    out = tmp_path / "poses.jsonl"
    args = argparse.Namespace(files=[str(tmp_path / "rec")], config=None, out=str(out))
    assert run(args) == 0
    assert "malformed=2" in capsys.readouterr().err


def test_replay_names_the_files_it_skips_and_why(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _record(tmp_path / "rec")
    (tmp_path / "rec" / "notes.txt").write_text("operator notes")
    (tmp_path / "rec" / "orbitar-000007.orec").write_bytes(b"")  # the disk filled at creation
    newer = {"k": "header", "t": 0, "d": {"format": "orbitar-recording", "version": 9}}
    (tmp_path / "rec" / "orbitar-000008.orec").write_bytes(msgpack.packb(newer))
    args = argparse.Namespace(files=[str(tmp_path / "rec")], config=None, out=None)
    assert run(args) == 0
    err = capsys.readouterr().err
    assert f"skipped {tmp_path / 'rec' / 'notes.txt'}: not named orbitar-NNNNNN.orec" in err
    assert "orbitar-000007.orec: empty (no header was written)" in err
    assert "orbitar-000008.orec: recording format version 9 not supported" in err
    assert "skipped_files=3" in err
    assert "poses=11" in err  # the good file was replayed whole
