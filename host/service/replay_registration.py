"""`orbitar replay`: re-run the link, the clock sync and the registration on a recording.

A recording made with raw link bytes (its header says `link_bytes`) is replayed from those bytes:
`LinkReplay` decodes them, re-fits the controller clock from the recorded CLOCK_SYNC probes and
converts every sample to host time, so the clock sync and the drift filter (reference marks,
rangefinder fixes in the pose feed) run again, not only the registration. Older recordings, and
stretches before the replayed link has synced, use the decoded sample records. Every recorded
frame (or, without a camera, every published pose) asks the registration for the camera pose at
its time again. The configuration comes from the recording's header unless `--config` names one.
The same recording and configuration always give the same output.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from host.config import Config, load_config, loads_config
from host.config_fields import ConfigError
from host.recording.link_replay import LinkReplay
from host.recording.reader import Record, RecordingError, RecordingReader
from host.recording.replay import SAMPLE_KINDS, ReplayStats, replay
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
from host.service.wiring import build_pose_source, exposure_latency_ms
from protocol import Stream

# The replay buffers must hold whatever rate was recorded: size them for the fastest stream.
REPLAY_RATES_HZ = {Stream.ENCODER: 1000, Stream.HEAD: 1000, Stream.RANGE: 1000}
SOURCES = ("auto", "raw", "decoded")
DECODED_SAMPLES = (KIND_ENCODER, KIND_HEAD, KIND_RANGE)


class ReplayRegistration:
    """A replay callback: samples into the buffers, frame and pose times out as poses."""

    def __init__(self, config: Config, source: str = "auto") -> None:
        if source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, not {source!r}")
        self.source_choice = source
        self.source, self.feed = build_pose_source(
            config, REPLAY_RATES_HZ, exposure_latency_ms(config), self._pitch_mm
        )
        self.link = LinkReplay(self.feed)
        # Without a camera the daemon published poses at the current time: no exposure latency.
        self.no_camera = dataclasses.replace(self.source, exposure_latency_ns=0)
        self.raw = source == "raw"
        self.malformed = 0  # sample records missing a field or holding a wrong type: skipped
        self.decoded_used = 0  # decoded sample records fed (no raw bytes, or not synced yet)
        self.clock_delta_max_ns = 0  # |live − replayed| host time of the same encoder sample
        self.pose_delta_max_mm = 0.0  # |live − replayed| camera position of the same pose
        self._last_frame_ns: int | None = None

    def _pitch_mm(self) -> float | None:
        """The chain pitch the replayed IDENTIFY reported (None before it, as live)."""
        link: LinkReplay | None = getattr(self, "link", None)
        return link.chain_pitch_mm if link is not None else None

    def __call__(self, record: Record) -> dict[str, Any] | None:
        """Feed one record; return the re-registered pose for frame and pose records."""
        try:
            return self._feed(record)
        except (KeyError, TypeError, ValueError, AttributeError):
            self.malformed += 1
            return None

    def _feed(self, record: Record) -> dict[str, Any] | None:
        """__call__ for a well-formed record (a bad field raises)."""
        d = record.data if isinstance(record.data, dict) else {}
        kind = record.kind
        if kind == KIND_HEADER:
            self.raw = self.source_choice == "raw" or (
                self.source_choice == "auto" and bool(d.get("link_bytes"))
            )
            if isinstance(d.get("link_identity"), dict):
                self.link.adopt_identity(d["link_identity"])
        elif kind == KIND_LINK:
            if self.raw:
                self.link.feed(str(d["dir"]), record.t_ns, bytes(d["bytes"]))
        elif kind in DECODED_SAMPLES or (kind == KIND_EVENT and "ref_mark_mm" in d):
            if self.raw and self.link.synced:
                self._compare_clock(record)
            else:
                self.decoded_used += 1
                self._feed_decoded(record, d)
        elif kind == KIND_FRAME:
            self._last_frame_ns = int(d.get("exposure_ns", record.t_ns))
            return self._pose(self._last_frame_ns, kind, self.source)
        elif kind == KIND_POSE:
            t_ns = int(d.get("t_ns", record.t_ns))
            camera = t_ns == self._last_frame_ns
            out = self._pose(t_ns, kind, self.source if camera else self.no_camera)
            self._compare_pose(out, d)
            return out
        return None

    def _feed_decoded(self, record: Record, d: dict[str, Any]) -> None:
        """A decoded sample record into the feed, as the link delivered it live."""
        if record.kind == KIND_ENCODER:
            s_mm, v_mm_s = float(d["s_mm"]), float(d.get("v_mm_s", 0.0))
            self.feed.on_encoder(record.t_ns, s_mm, v_mm_s, int(d.get("inputs", 0)))
        elif record.kind == KIND_HEAD:
            self.feed.on_head(record.t_ns, float(d["pan_rad"]), float(d["tilt_rad"]))
        elif record.kind == KIND_RANGE:
            distance_mm, quality = float(d["distance_mm"]), int(d.get("quality", 0))
            self.feed.on_range(record.t_ns, distance_mm, quality)
        else:
            self.feed.on_mark(record.t_ns, float(d["ref_mark_mm"]))

    def _compare_clock(self, record: Record) -> None:
        """A decoded encoder record beside its replayed twin: how far the clocks agree."""
        if record.kind == KIND_ENCODER and self.link.encoder_times_ns:
            delta = abs(record.t_ns - self.link.encoder_times_ns.popleft())
            self.clock_delta_max_ns = max(self.clock_delta_max_ns, delta)

    def _compare_pose(self, out: dict[str, Any], live: dict[str, Any]) -> None:
        """The recorded (live) pose beside the replayed one."""
        matrix = live.get("T_w_c")
        if "T_w_c" in out and isinstance(matrix, list):
            delta = np.asarray(out["T_w_c"])[:3, 3] - np.asarray(matrix, dtype=float)[:3, 3]
            self.pose_delta_max_mm = max(self.pose_delta_max_mm, float(np.linalg.norm(delta)))

    @staticmethod
    def _pose(t_ns: int, kind: str, source: Any) -> dict[str, Any]:
        """The camera pose at t_ns as the registration sees it now."""
        pose = source.pose_at(t_ns)
        out: dict[str, Any] = {"kind": kind, "t_ns": t_ns, "status": pose.status.value}
        if pose.T_w_c is not None:
            out.update(
                s_mm=round(pose.s_mm, 6),
                pan_rad=round(pose.pan_rad, 9),
                tilt_rad=round(pose.tilt_rad, 9),
                T_w_c=np.round(pose.T_w_c, 6).tolist(),
            )
        return out

    def summary(self) -> dict[str, Any]:
        """What the replayed link and the comparison with the live run found."""
        link = self.link.stats
        return {
            "source": "raw" if self.raw else "decoded",
            "link_frames": link.rx_frames + link.tx_frames,
            "probes_used": link.probes_used,
            "raw_samples": link.samples,
            "decoded_used": self.decoded_used,
            "clock_delta_max_us": round(self.clock_delta_max_ns / 1000, 3),
            "pose_delta_max_mm": round(self.pose_delta_max_mm, 6),
            "malformed": self.malformed,
        }


def add_parser(subparsers: Any) -> None:
    """`orbitar replay FILE… [--config PATH] [--source auto|raw|decoded] [--out FILE]`."""
    parser = subparsers.add_parser(
        "replay", help="re-run the link, clock sync and registration on a recording"
    )
    parser.add_argument("files", nargs="+", help="recording files or directories")
    parser.add_argument(
        "--config", help="daemon configuration (default: the one in the recording's header)"
    )
    parser.add_argument(
        "--source",
        choices=SOURCES,
        default="auto",
        help="samples from the raw link bytes, the decoded records, or raw when recorded (auto)",
    )
    parser.add_argument("--out", help="write the poses as JSON lines here instead of stdout")
    parser.set_defaults(handler=run)


def recorded_config(files: list[str]) -> tuple[Config, str]:
    """The configuration in the first readable header, and where it came from."""
    reader = RecordingReader(files)
    for record in reader:
        if record.kind != KIND_HEADER:
            continue
        text = record.data.get("config_toml") if isinstance(record.data, dict) else None
        if not isinstance(text, str):
            return Config(), f"built-in defaults ({record.file} has no configuration)"
        try:
            config = loads_config(text) if text.strip() else Config()
        except ConfigError as exc:
            raise ConfigError([f"{record.file} header: {p}" for p in exc.problems]) from exc
        origin = record.data.get("config_path") or "built-in defaults"
        return config, f"{origin}, as recorded in {record.file}"
    return Config(), "built-in defaults (no readable header)"


def run(args: argparse.Namespace) -> int:
    """Replay and print (or write) one JSON line per re-registered pose, then a summary."""
    try:
        if args.config:
            config, origin = load_config(args.config), args.config
        else:
            config, origin = recorded_config(args.files)
    except (ConfigError, OSError) as exc:
        print(f"orbitar replay: {exc}", file=sys.stderr)
        return 2
    print(f"orbitar replay: configuration from {origin}", file=sys.stderr)
    registration = ReplayRegistration(config, getattr(args, "source", "auto"))
    try:
        stats = replay(args.files, registration, kinds=SAMPLE_KINDS | {KIND_HEADER})
    except (RecordingError, OSError) as exc:
        print(f"orbitar replay: {exc}", file=sys.stderr)
        return 1
    for path, why in stats.skipped:
        print(f"orbitar replay: skipped {path}: {why}", file=sys.stderr)
    if stats.files_read == 0:
        print("orbitar replay: no readable recording among the files given", file=sys.stderr)
        return 1
    lines = "".join(json.dumps(result, sort_keys=True) + "\n" for result in stats.results)
    if args.out:
        Path(args.out).write_text(lines, encoding="utf-8")
    else:
        sys.stdout.write(lines)
    print(" ".join(f"{k}={v}" for k, v in _summary(stats, registration).items()), file=sys.stderr)
    return 0


def _summary(stats: ReplayStats, registration: ReplayRegistration) -> dict[str, Any]:
    """The stderr summary line's fields."""
    counts = {k: v for k, v in sorted(stats.by_kind.items()) if k != KIND_HEADER}
    return {
        **counts,
        "records": stats.records,
        "poses": len(stats.results),
        "files": stats.files_read,
        "skipped_files": len(stats.skipped),
        "truncated_bytes": stats.truncated_bytes,
        "corrupt_files": stats.corrupt_files,
        **registration.summary(),
    }
