"""`orbitar replay`: re-run the registration on a recording, deterministically.

Encoder, head, rangefinder and reference-mark records refill the pose buffers exactly as the
link filled them; every recorded frame (or, without a camera, every published pose) asks the
registration for the camera pose at its time again. The same recording and configuration always
give the same output, so a replay can be compared with what the daemon published or with a new
build.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from host.config import Config, load_config
from host.config_fields import ConfigError
from host.recording.reader import Record, RecordingError
from host.recording.replay import replay
from host.recording.writer import (
    KIND_ENCODER,
    KIND_EVENT,
    KIND_FRAME,
    KIND_HEAD,
    KIND_POSE,
    KIND_RANGE,
)
from host.service.wiring import build_pose_source, exposure_latency_ms
from protocol import Stream

# The replay buffers must hold whatever rate was recorded: size them for the fastest stream.
REPLAY_RATES_HZ = {Stream.ENCODER: 1000, Stream.HEAD: 1000, Stream.RANGE: 1000}


class ReplayRegistration:
    """A replay callback: samples into the buffers, frame and pose times out as poses."""

    def __init__(self, config: Config) -> None:
        self.source, self.feed = build_pose_source(
            config, REPLAY_RATES_HZ, exposure_latency_ms(config)
        )
        self.malformed = 0  # sample records missing a field or holding a wrong type: skipped

    def __call__(self, record: Record) -> dict[str, Any] | None:
        """Feed one record; return the re-registered pose for frame and pose records."""
        try:
            return self._feed(record)
        except (KeyError, TypeError, ValueError):
            self.malformed += 1
            return None

    def _feed(self, record: Record) -> dict[str, Any] | None:
        """__call__ for a well-formed record (a bad field raises)."""
        d = record.data if isinstance(record.data, dict) else {}
        if record.kind == KIND_ENCODER:
            s_mm, v_mm_s = float(d["s_mm"]), float(d.get("v_mm_s", 0.0))
            self.feed.on_encoder(record.t_ns, s_mm, v_mm_s, int(d.get("inputs", 0)))
        elif record.kind == KIND_HEAD:
            self.feed.on_head(record.t_ns, float(d["pan_rad"]), float(d["tilt_rad"]))
        elif record.kind == KIND_RANGE:
            distance_mm, quality = float(d["distance_mm"]), int(d.get("quality", 0))
            self.feed.on_range(record.t_ns, distance_mm, quality)
        elif record.kind == KIND_EVENT and "ref_mark_mm" in d:
            self.feed.on_mark(record.t_ns, float(d["ref_mark_mm"]))
        elif record.kind in (KIND_FRAME, KIND_POSE):
            return self._pose(int(d.get("exposure_ns", record.t_ns)), record.kind)
        return None

    def _pose(self, t_ns: int, kind: str) -> dict[str, Any]:
        """The camera pose at t_ns as the registration sees it now."""
        pose = self.source.pose_at(t_ns)
        out: dict[str, Any] = {"kind": kind, "t_ns": t_ns, "status": pose.status.value}
        if pose.T_w_c is not None:
            out.update(
                s_mm=round(pose.s_mm, 6),
                pan_rad=round(pose.pan_rad, 9),
                tilt_rad=round(pose.tilt_rad, 9),
                T_w_c=np.round(pose.T_w_c, 6).tolist(),
            )
        return out


def add_parser(subparsers: Any) -> None:
    """`orbitar replay FILE… [--config PATH] [--out FILE]`."""
    parser = subparsers.add_parser(
        "replay", help="re-run the registration on a recording and print the poses"
    )
    parser.add_argument("files", nargs="+", help="recording files or directories")
    parser.add_argument("--config", help="daemon configuration (default: the built-in rig)")
    parser.add_argument("--out", help="write the poses as JSON lines here instead of stdout")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Replay and print (or write) one JSON line per re-registered pose, then a summary."""
    try:
        config = load_config(args.config) if args.config else Config()
    except (ConfigError, OSError) as exc:
        print(f"orbitar replay: {exc}", file=sys.stderr)
        return 2
    registration = ReplayRegistration(config)
    try:
        stats = replay(args.files, registration)
    except (RecordingError, OSError) as exc:
        print(f"orbitar replay: {exc}", file=sys.stderr)
        return 1
    lines = "".join(json.dumps(result, sort_keys=True) + "\n" for result in stats.results)
    if args.out:
        Path(args.out).write_text(lines, encoding="utf-8")
    else:
        sys.stdout.write(lines)
    summary = {
        **dict(sorted(stats.by_kind.items())),
        "records": stats.records,
        "poses": len(stats.results),
        "truncated_bytes": stats.truncated_bytes,
        "corrupt_files": stats.corrupt_files,
        "malformed": registration.malformed,
    }
    print(" ".join(f"{k}={v}" for k, v in summary.items()), file=sys.stderr)
    return 0
