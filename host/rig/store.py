"""Writing the rig file as calibration does: validated, atomic, keeping the previous versions.

Like Klipper's SAVE_CONFIG: the new file is written beside the old one, flushed to disk and
renamed over it, so a crash or a full disk leaves either the old file or the new one, never a
half-written one; the old file is kept as `NAME.YYYYmmdd-HHMMSS.bak` (the newest
`KEEP_BACKUPS`). A calibration that failed its threshold must not call these at all.
"""

from __future__ import annotations

import dataclasses
import datetime
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from host.rig.codec import RigError, dumps_rig, load_rig, loads_rig
from host.rig.schema import RigSpec, utc_now

KEEP_BACKUPS = 5
BACKUP_SUFFIX = ".bak"
# The blocks a calibration may replace, by dotted name (each holds its own provenance).
UPDATABLE = (
    "track.placement",
    "track.home",
    "track.marks",
    "track.segments",  # the arcs' radii (survey track), with:
    "track.arc_radius_sigma_mm",
    "track.arcs",
    "hall",
    "head.m_cr",
    "head.angle_noise",
    "rangefinder.mount",
    "camera.intrinsics",
    "camera.latency",
    "workpiece.frame",
    "covariance",
)


def save_rig(spec: RigSpec, path: str | Path, note: str = "") -> Path | None:
    """Write `spec` atomically; return the backup of the file it replaced (None if new)."""
    target = Path(path)
    header = f"Orbitar rig file, written {utc_now()}" + (f": {note}" if note else "")
    text = dumps_rig(spec, header + "\nWritten by Orbitar; previous versions kept as *.bak.")
    loads_rig(text)  # never write what we could not read back
    backup = _backup(target)
    _atomic_write(target, text)
    _prune(target)
    return backup


def with_updates(spec: RigSpec, updates: Mapping[str, Any]) -> RigSpec:
    """A copy of `spec` with calibrated blocks replaced, e.g. {"head.m_cr": Pose6(...)}.

    Replacing a block the joint `covariance` covers, without a new one, drops it: its cross
    terms were of the old values.
    """
    joint = spec.covariance
    if joint is not None and "covariance" not in updates and set(updates) & set(joint.names):
        spec = dataclasses.replace(spec, covariance=None)
    for key, value in updates.items():
        if key not in UPDATABLE:
            raise RigError([f"{key}: not a calibrated block (known: {', '.join(UPDATABLE)})"])
        section, _, attr = key.partition(".")
        if not attr:
            spec = dataclasses.replace(spec, **{section: value})
            continue
        inner = dataclasses.replace(getattr(spec, section), **{attr: value})
        spec = dataclasses.replace(spec, **{section: inner})
    return spec


def update_rig(path: str | Path, updates: Mapping[str, Any], note: str = "") -> RigSpec:
    """Read the rig file, replace calibrated blocks, validate and save atomically; the new spec.

    The file must exist and be valid (RigError otherwise, nothing written); each replacement
    carries its σ and `Provenance` (method, date, residual, views).
    """
    new = with_updates(load_rig(path), updates)
    loads_rig(dumps_rig(new))  # validate the result as the daemon will read it
    save_rig(new, path, note)
    return new


def backups(path: str | Path) -> list[Path]:
    """The kept previous versions of a rig file, oldest first."""
    target = Path(path)
    return sorted(target.parent.glob(f"{target.name}.*{BACKUP_SUFFIX}"))


def _backup(target: Path) -> Path | None:
    """Copy the current file to a timestamped backup (by hard link when possible)."""
    if not target.exists():
        return None
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%d-%H%M%S-%f")
    backup = target.with_name(f"{target.name}.{stamp}{BACKUP_SUFFIX}")
    _atomic_write(backup, target.read_text(encoding="utf-8"))
    return backup


def _atomic_write(target: Path, text: str) -> None:
    """Temp file in the same directory, fsync, rename over the target, fsync the directory."""
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if target.exists():
            os.chmod(tmp, target.stat().st_mode & 0o777)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(target.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _prune(target: Path) -> None:
    """Keep only the newest KEEP_BACKUPS backups."""
    for old in backups(target)[:-KEEP_BACKUPS]:
        old.unlink(missing_ok=True)


_cache: dict[str, tuple[tuple[int, int], RigSpec]] = {}


def current_rig(path: str | Path) -> RigSpec:
    """The rig file as it is now (reread only when it changed); "" is the paper's nominal rig."""
    if not str(path):
        return RigSpec()
    try:
        st = os.stat(path)
    except OSError as exc:
        raise RigError([f"rig.path = {str(path)!r}: cannot read: {exc}"]) from None
    stamp = (st.st_mtime_ns, st.st_size)
    cached = _cache.get(str(path))
    if cached is not None and cached[0] == stamp:
        return cached[1]
    spec = load_rig(path)
    _cache[str(path)] = (stamp, spec)
    return spec
