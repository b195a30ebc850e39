"""Rig file ↔ `RigSpec`: TOML in, every problem named by its dotted key and reason; TOML out.

Reading collects all problems and raises one `RigError` (a `ConfigError`, so the daemon and
`orbitar config check` report it as they report the config). Writing emits the whole rig, so a
written file reads back to an equal `RigSpec` (round trip). No TOML writer is in the standard
library; the emitter below covers exactly the value types this schema has.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from host.config_fields import ConfigError
from host.geometry.head import rotation_problem
from host.geometry.rangefinder import unit_normal
from host.geometry.track import Track
from host.rig.covariance import joint_problems
from host.rig.schema import (
    COVARIANCE_BLOCKS,
    FORMAT_VERSION,
    INTRINSIC_KEYS,
    SEGMENT_KINDS,
    CameraSpec,
    ChainSpec,
    HallSpec,
    HeadSpec,
    Intrinsics,
    JointCovariance,
    Marks,
    Pose6,
    Provenance,
    RangefinderSpec,
    RigSpec,
    Scalar,
    Segment,
    SurfaceSpec,
    TrackSpec,
    WorkpieceSpec,
)

DEG_DIGITS = 10  # decimals of a written angle: far below any tolerance, stable on rereading


class RigError(ConfigError):
    """A rig file is wrong; `problems` lists every `key = value: reason` found."""


class _Reader:
    """Typed reads from one table, recording `prefix.key = value: reason` problems."""

    def __init__(self, table: Any, prefix: str, problems: list[str], known: tuple[str, ...]):
        self.prefix, self.problems = prefix, problems
        if not isinstance(table, dict):
            problems.append(f"{prefix.rstrip('.') or '(top)'} = {table!r}: expected a table")
            table = {}
        self.table: dict[str, Any] = table
        for key in table:
            if key not in known:
                problems.append(f"{prefix}{key}: unknown key (known: {', '.join(sorted(known))})")

    def key(self, name: str) -> str:
        return self.prefix + name

    def fail(self, name: str, reason: str) -> None:
        value = self.table.get(name)
        self.problems.append(f"{self.key(name)} = {value!r}: {reason}")

    def has(self, name: str) -> bool:
        return name in self.table

    def sub(self, name: str, known: tuple[str, ...]) -> _Reader:
        return _Reader(self.table.get(name, {}), self.key(name) + ".", self.problems, known)

    def number(
        self, name: str, default: float, lo: float = -math.inf, hi: float = math.inf
    ) -> float:
        if name not in self.table:
            return default
        v = self.table[name]
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            self.fail(name, "expected a finite number")
            return default
        if not lo <= v <= hi:
            self.fail(name, f"out of range [{lo:g}, {hi:g}]")
            return default
        return float(v)

    def optional(self, name: str, lo: float = -math.inf, hi: float = math.inf) -> float | None:
        return self.number(name, math.nan, lo, hi) if name in self.table else None

    def integer(self, name: str, default: int, lo: int, hi: int) -> int:
        v = self.table.get(name, default)
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(name, "expected an integer")
            return default
        if not lo <= v <= hi:
            self.fail(name, f"out of range [{lo}, {hi}]")
            return default
        return v

    def text(self, name: str, default: str) -> str:
        v = self.table.get(name, default)
        if not isinstance(v, str):
            self.fail(name, "expected a string")
            return default
        return v

    def flag(self, name: str, default: bool | None) -> bool | None:
        v = self.table.get(name, default)
        if v is not None and not isinstance(v, bool):
            self.fail(name, "expected true or false")
            return default
        return v

    def numbers(
        self, name: str, default: tuple[float, ...], size: int | None = None
    ) -> tuple[float, ...]:
        if name not in self.table:
            return default
        v = self.table[name]
        ok = isinstance(v, list) and all(
            not isinstance(x, bool) and isinstance(x, int | float) and math.isfinite(x) for x in v
        )
        if not ok:
            self.fail(name, "expected a list of finite numbers")
            return default
        if size is not None and len(v) != size:
            self.fail(name, f"expected {size} numbers, got {len(v)}")
            return default
        return tuple(float(x) for x in v)

    def matrix(self, name: str, rows: int, default: Any) -> Any:
        if name not in self.table:
            return default
        v = self.table[name]
        shape_ok = isinstance(v, list) and len(v) == rows
        shape_ok = shape_ok and all(isinstance(r, list) and len(r) == rows for r in v)
        if not shape_ok or any(
            isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x)
            for r in v
            for x in r
        ):
            self.fail(name, f"expected a {rows}×{rows} list of finite numbers")
            return default
        return np.array(v, dtype=np.float64)


# ---- reading --------------------------------------------------------------------------------

_PROV_KEYS = ("method", "date", "residual", "residual_unit", "views", "note")
_POSE_KEYS = ("matrix", "sigma_rad", "sigma_mm", "covariance", "provenance")


def _provenance(r: _Reader) -> Provenance:
    p = r.sub("provenance", _PROV_KEYS)
    views = p.integer("views", 0, 0, 10**9) if p.has("views") else None
    return Provenance(
        p.text("method", "nominal"),
        p.text("date", ""),
        p.optional("residual", 0.0),
        p.text("residual_unit", ""),
        views,
        p.text("note", ""),
    )


def _sigma3(r: _Reader, name: str) -> tuple[float, float, float]:
    vals = r.numbers(name, (0.0, 0.0, 0.0), size=3)
    if any(v < 0 for v in vals):
        r.fail(name, "standard deviations must be >= 0")
        return (0.0, 0.0, 0.0)
    return (vals[0], vals[1], vals[2])


def _pose(r: _Reader, name: str, default: Pose6) -> Pose6:
    if not r.has(name):
        return default
    p = r.sub(name, _POSE_KEYS)
    matrix = p.matrix("matrix", 4, None)
    if matrix is None:
        if not p.has("matrix"):
            p.fail("matrix", "required (the 4×4 transform, rows, mm)")
        matrix = default.matrix
    elif not np.allclose(matrix[3], [0, 0, 0, 1]):
        p.fail("matrix", "the last row of a homogeneous transform must be [0, 0, 0, 1]")
    elif (problem := rotation_problem(matrix)) is not None:  # the config's rule (printed figures)
        p.fail("matrix", problem)
    cov = p.matrix("covariance", 6, None)
    if cov is not None and (
        not np.allclose(cov, cov.T) or np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() < -1e-12
    ):
        p.fail("covariance", "must be symmetric positive semi-definite")
        cov = None
    return Pose6(matrix, _sigma3(p, "sigma_rad"), _sigma3(p, "sigma_mm"), cov, _provenance(p))


def _scalar(r: _Reader, name: str, default: Scalar, unit: str, lo: float, hi: float) -> Scalar:
    if not r.has(name):
        return default
    p = r.sub(name, (f"value_{unit}", f"sigma_{unit}", "provenance"))
    value = p.number(f"value_{unit}", default.value, lo, hi)
    sigma = p.number(f"sigma_{unit}", default.sigma, 0.0)
    return Scalar(value, sigma, _provenance(p))


def _segment(r: _Reader) -> Segment:
    kind = r.text("kind", "")
    if kind not in SEGMENT_KINDS:
        r.fail("kind", f"must be one of {', '.join(SEGMENT_KINDS)}")
        return Segment("straight", 1.0)
    if kind == "straight":
        length = r.number("length_mm", 0.0, 0.0, 1e6)
        if not length > 0:
            r.fail("length_mm", "a straight needs a positive length")
        return Segment("straight", length)
    radius = r.number("radius_mm", 0.0, 0.0, 1e6)
    angle = r.number("angle_deg", 0.0, -360.0, 360.0)
    if not radius > 0 or angle == 0:
        r.problems.append(f"{r.prefix.rstrip('.')}: an arc needs radius_mm > 0 and angle_deg != 0")
    return Segment("arc", 0.0, radius, math.radians(angle))


def _table_array(r: _Reader, name: str, known: tuple[str, ...]) -> list[_Reader]:
    items = r.table.get(name, [])
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        r.fail(name, "expected an array of tables")
        return []
    return [_Reader(t, f"{r.key(name)}[{i}].", r.problems, known) for i, t in enumerate(items)]


def _track(r: _Reader, default: TrackSpec) -> TrackSpec:
    t = r.sub(
        "track",
        (
            "segments", "placement", "closed", "home", "marks", "travel_min_mm", "travel_max_mm",
            "arc_radius_sigma_mm", "chain", "arcs",
        ),
    )  # fmt: skip
    segments = default.segments
    if t.has("segments"):
        known = ("kind", "length_mm", "radius_mm", "angle_deg")
        segments = tuple(_segment(sr) for sr in _table_array(t, "segments", known))
        if not segments:
            t.fail("segments", "a track needs at least one segment")
            segments = default.segments
    m = t.sub("marks", ("s_mm", "sigma_mm", "provenance"))
    marks = Marks(
        m.numbers("s_mm", ()), m.number("sigma_mm", default.marks.sigma_mm, 0.0), _provenance(m)
    )
    spec = TrackSpec(
        segments,
        _pose(t, "placement", default.placement),
        t.flag("closed", None),
        _scalar(t, "home", default.home, "mm", -1e6, 1e6),  # a loop's zero may lie before s = 0
        marks,
        t.optional("travel_min_mm", -1e6, 1e6),
        t.optional("travel_max_mm", -1e6, 1e7),
        t.number("arc_radius_sigma_mm", default.arc_radius_sigma_mm, 0.0, 1e3),
        _chain(t.sub("chain", ("sprocket_teeth", "pitch_mm")), default.chain),
        _provenance(t.sub("arcs", ("provenance",))) if t.has("arcs") else default.arcs,
    )
    _track_checks(spec, r.problems)
    return spec


def _chain(c: _Reader, default: ChainSpec) -> ChainSpec:
    # teeth: the smallest roller-chain sprockets have 6-9; pitch: ISO 04 (6 mm) to 32B (51 mm)
    return ChainSpec(
        c.integer("sprocket_teeth", default.sprocket_teeth, 6, 255),
        c.number("pitch_mm", default.pitch_mm, 3.0, 100.0),
    )


def _track_checks(spec: TrackSpec, problems: list[str]) -> None:
    """The path is drawable; home, marks and travel lie on it; closed only if it closes."""
    try:
        Track.from_config(
            [s.as_geometry() for s in spec.segments], spec.placement.matrix, spec.closed
        )
    except (ValueError, KeyError) as exc:
        problems.append(f"track.closed = {spec.closed!r}: {exc}")
        return
    length = spec.length_mm
    if spec.home.value > length:
        problems.append(
            f"track.home.value_mm = {spec.home.value}: beyond the track's {length:.1f} mm"
        )
    for i, s in enumerate(spec.marks.s_mm):
        if not 0.0 <= s <= length:
            problems.append(f"track.marks.s_mm[{i}] = {s}: outside the track [0, {length:.1f}] mm")
        if i and s <= spec.marks.s_mm[i - 1]:
            problems.append(f"track.marks.s_mm[{i}] = {s}: must be above the previous mark")
    lo, hi = spec.travel_min_mm, spec.travel_max_mm
    if lo is not None and hi is not None and lo >= hi:
        problems.append(f"track.travel_min_mm = {lo}: must be below track.travel_max_mm = {hi}")


def _hall(r: _Reader) -> HallSpec:
    h = r.sub("hall", ("surfaces", "provenance"))
    known = ("name", "point_mm", "normal", "radius_mm", "sigma_mm")
    surfaces = []
    for s in _table_array(h, "surfaces", known):
        name = s.text("name", "")
        if not name:
            s.fail("name", "required")
        point = s.numbers("point_mm", (0.0, 0.0, 0.0), size=3)
        normal = s.numbers("normal", (0.0, 0.0, 1.0), size=3)
        try:
            unit_normal(normal)
        except ValueError as exc:
            s.fail("normal", str(exc))
        surfaces.append(
            SurfaceSpec(
                name,
                (point[0], point[1], point[2]),
                (normal[0], normal[1], normal[2]),
                s.number("radius_mm", 0.0, 0.0, 1e6),
                s.number("sigma_mm", 1.0, 0.0, 1e3),
            )
        )
    return HallSpec(tuple(surfaces), _provenance(h))


def _head(r: _Reader, default: HeadSpec) -> HeadSpec:
    h = r.sub(
        "head",
        ("m_cr", "pan_min_deg", "pan_max_deg", "tilt_min_deg", "tilt_max_deg", "angle_noise"),
    )

    def deg(name: str, value: float, lim: float) -> float:
        return math.radians(h.number(name, math.degrees(value), -lim, lim))

    spec = HeadSpec(
        _pose(h, "m_cr", default.m_cr),
        deg("pan_min_deg", default.pan_min_rad, 360.0),
        deg("pan_max_deg", default.pan_max_rad, 360.0),
        deg("tilt_min_deg", default.tilt_min_rad, 180.0),
        deg("tilt_max_deg", default.tilt_max_rad, 180.0),
        _scalar(h, "angle_noise", default.angle_noise, "rad", -0.1, 0.1),
    )
    if spec.pan_min_rad >= spec.pan_max_rad:
        h.fail("pan_min_deg", "must be below head.pan_max_deg")
    if spec.tilt_min_rad >= spec.tilt_max_rad:
        h.fail("tilt_min_deg", "must be below head.tilt_max_deg")
    return spec


def _rangefinder(r: _Reader, default: RangefinderSpec) -> RangefinderSpec:
    f = r.sub("rangefinder", ("mount", "noise_mm", "min_mm", "max_mm"))
    spec = RangefinderSpec(
        _pose(f, "mount", default.mount),
        f.number("noise_mm", default.noise_mm, 1e-3, 1e3),
        f.number("min_mm", default.min_mm, 0.0, 1e6),
        f.number("max_mm", default.max_mm, 0.0, 1e6),
    )
    if spec.min_mm >= spec.max_mm:
        f.fail("min_mm", "must be below rangefinder.max_mm")
    return spec


def _intrinsics(r: _Reader, default: Intrinsics) -> Intrinsics:
    i = r.sub("intrinsics", (*INTRINSIC_KEYS, "sigma", "covariance", "provenance"))
    values = tuple(
        i.number(k, v, -1e6, 1e6) for k, v in zip(INTRINSIC_KEYS, default.values, strict=True)
    )
    for k in ("fx", "fy"):
        if values[INTRINSIC_KEYS.index(k)] <= 0:
            i.fail(k, "a focal length must be > 0")
    s = i.sub("sigma", INTRINSIC_KEYS)
    sigma = tuple(s.number(k, v, 0.0) for k, v in zip(INTRINSIC_KEYS, default.sigma, strict=True))
    cov = i.matrix("covariance", len(INTRINSIC_KEYS), None)
    cov_t = None if cov is None else tuple(tuple(float(x) for x in row) for row in cov)
    return Intrinsics(values, sigma, cov_t, _provenance(i))


def _camera(r: _Reader, default: CameraSpec) -> CameraSpec:
    c = r.sub(
        "camera", ("width", "height", "fps", "intrinsics", "latency", "trigger", "clock_sync")
    )
    return CameraSpec(
        c.integer("width", default.width, 1, 16384),
        c.integer("height", default.height, 1, 16384),
        c.number("fps", default.fps, 0.1, 1000.0),
        _intrinsics(c, default.intrinsics),
        _scalar(c, "latency", default.latency, "ms", -1000.0, 1000.0),
        bool(c.flag("trigger", default.trigger)),
        _scalar(c, "clock_sync", default.clock_sync, "ms", -1000.0, 1000.0),
    )


def _workpiece(r: _Reader, default: WorkpieceSpec) -> WorkpieceSpec:
    w = r.sub("workpiece", ("frame", "model"))
    model = w.text("model", default.model)
    if not model:
        w.fail("model", 'a model file or "builtin:manipulator"')
    return WorkpieceSpec(_pose(w, "frame", default.frame), model)


def _covariance(r: _Reader, default: JointCovariance | None) -> JointCovariance | None:
    """The joint block; its agreement with the blocks it names is checked on the whole rig."""
    if not r.has("covariance"):
        return default
    c = r.sub("covariance", ("names", "matrix", "provenance"))
    names = c.table.get("names")
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        c.fail("names", "expected a list of block names")
        return default
    if not names or any(n not in COVARIANCE_BLOCKS for n in names):
        c.fail("names", f"name known blocks ({', '.join(COVARIANCE_BLOCKS)})")
        return default
    size = sum(COVARIANCE_BLOCKS[n] for n in names)
    matrix = c.matrix("matrix", size, None)
    if matrix is None:
        if not c.has("matrix"):
            c.fail("matrix", f"required ({size}×{size} over the named blocks)")
        return default
    return JointCovariance(tuple(names), matrix, _provenance(c))


_SECTIONS: dict[str, Callable[[_Reader, RigSpec], Any]] = {
    "track": lambda r, d: _track(r, d.track),
    "hall": lambda r, d: _hall(r) if r.has("hall") else d.hall,
    "head": lambda r, d: _head(r, d.head),
    "rangefinder": lambda r, d: _rangefinder(r, d.rangefinder),
    "camera": lambda r, d: _camera(r, d.camera),
    "workpiece": lambda r, d: _workpiece(r, d.workpiece),
    "covariance": lambda r, d: _covariance(r, d.covariance),
}


def rig_from_dict(table: Mapping[str, Any], base: RigSpec | None = None) -> RigSpec:
    """Validate a parsed rig table; missing sections and keys come from `base` (the paper's rig)."""
    problems: list[str] = []
    default = base or RigSpec()
    r = _Reader(dict(table), "", problems, ("format", "name", *_SECTIONS))
    version = r.integer("format", FORMAT_VERSION, 1, 10**6)
    if version != FORMAT_VERSION:
        r.fail("format", f"this Orbitar reads rig format {FORMAT_VERSION}")
    parts = {name: read(r, default) for name, read in _SECTIONS.items()}
    spec = RigSpec(name=r.text("name", default.name), **parts)
    problems += joint_problems(spec)
    if problems:
        raise RigError(problems)
    return spec


def loads_rig(text: str) -> RigSpec:
    """Validate TOML text into a RigSpec."""
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RigError([f"TOML syntax: {exc}"]) from exc
    return rig_from_dict(table)


def load_rig(path: str | Path) -> RigSpec:
    """Read and validate a rig file; RigError lists every problem, naming the dotted key."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RigError([f"{path}: cannot read: {exc}"]) from exc
    try:
        return loads_rig(text)
    except RigError as exc:
        raise RigError([f"{path}: {p}" for p in exc.problems]) from None


# ---- writing --------------------------------------------------------------------------------


def rig_to_dict(spec: RigSpec) -> dict[str, Any]:
    """The rig as plain TOML-ready data (degrees in `_deg` keys, as the reader expects)."""
    t = spec.track
    track: dict[str, Any] = {
        "segments": [_segment_dict(s) for s in t.segments],
        "placement": _pose_dict(t.placement),
        "home": _scalar_dict(t.home, "mm"),
        "marks": {
            "s_mm": list(t.marks.s_mm),
            "sigma_mm": t.marks.sigma_mm,
            "provenance": _prov_dict(t.marks.provenance),
        },
    }
    track["arc_radius_sigma_mm"] = t.arc_radius_sigma_mm
    track["chain"] = {"sprocket_teeth": t.chain.sprocket_teeth, "pitch_mm": t.chain.pitch_mm}
    if t.arcs != Provenance():
        track["arcs"] = {"provenance": _prov_dict(t.arcs)}
    for key in ("closed", "travel_min_mm", "travel_max_mm"):
        if getattr(t, key) is not None:
            track[key] = getattr(t, key)
    cam, head, rf = spec.camera, spec.head, spec.rangefinder
    intr = cam.intrinsics
    intrinsics: dict[str, Any] = dict(intr.as_dict())
    intrinsics["sigma"] = dict(zip(INTRINSIC_KEYS, intr.sigma, strict=True))
    if intr.covariance is not None:
        intrinsics["covariance"] = [list(row) for row in intr.covariance]
    intrinsics["provenance"] = _prov_dict(intr.provenance)
    out: dict[str, Any] = {
        "format": FORMAT_VERSION,
        "name": spec.name,
        "track": track,
        "hall": {
            "surfaces": [_surface_dict(s) for s in spec.hall.surfaces],
            "provenance": _prov_dict(spec.hall.provenance),
        },
        "head": {
            "pan_min_deg": _deg(head.pan_min_rad),
            "pan_max_deg": _deg(head.pan_max_rad),
            "tilt_min_deg": _deg(head.tilt_min_rad),
            "tilt_max_deg": _deg(head.tilt_max_rad),
            "angle_noise": _scalar_dict(head.angle_noise, "rad"),
            "m_cr": _pose_dict(head.m_cr),
        },
        "rangefinder": {
            "noise_mm": rf.noise_mm,
            "min_mm": rf.min_mm,
            "max_mm": rf.max_mm,
            "mount": _pose_dict(rf.mount),
        },
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "fps": cam.fps,
            "trigger": cam.trigger,
            "intrinsics": intrinsics,
            "latency": _scalar_dict(cam.latency, "ms"),
            "clock_sync": _scalar_dict(cam.clock_sync, "ms"),
        },
        "workpiece": {"model": spec.workpiece.model, "frame": _pose_dict(spec.workpiece.frame)},
    }
    if spec.covariance is not None:
        out["covariance"] = {
            "names": list(spec.covariance.names),
            "matrix": spec.covariance.matrix.tolist(),
            "provenance": _prov_dict(spec.covariance.provenance),
        }
    return out


def _deg(angle_rad: float) -> float:
    """Degrees for the file, rounded so that a written file reads and writes back identically."""
    return round(math.degrees(angle_rad), DEG_DIGITS)


def _segment_dict(s: Segment) -> dict[str, Any]:
    if s.kind == "straight":
        return {"kind": "straight", "length_mm": s.length_mm}
    return {"kind": "arc", "radius_mm": s.radius_mm, "angle_deg": _deg(s.angle_rad)}


def _surface_dict(s: SurfaceSpec) -> dict[str, Any]:
    return {
        "name": s.name,
        "point_mm": list(s.point_mm),
        "normal": list(s.normal),
        "radius_mm": s.radius_mm,
        "sigma_mm": s.sigma_mm,
    }


def _prov_dict(p: Provenance) -> dict[str, Any]:
    out: dict[str, Any] = {"method": p.method, "date": p.date}
    if p.residual is not None:
        out["residual"] = p.residual
        out["residual_unit"] = p.residual_unit
    if p.views is not None:
        out["views"] = p.views
    if p.note:
        out["note"] = p.note
    return out


def _pose_dict(p: Pose6) -> dict[str, Any]:
    out: dict[str, Any] = {
        "matrix": p.matrix.tolist(),
        "sigma_rad": list(p.sigma_rad),
        "sigma_mm": list(p.sigma_mm),
    }
    if p.covariance is not None:
        out["covariance"] = p.covariance.tolist()
    out["provenance"] = _prov_dict(p.provenance)
    return out


def _scalar_dict(s: Scalar, unit: str) -> dict[str, Any]:
    return {
        f"value_{unit}": s.value,
        f"sigma_{unit}": s.sigma,
        "provenance": _prov_dict(s.provenance),
    }


def dumps_rig(spec: RigSpec, header: str = "") -> str:
    """The rig as TOML text that `loads_rig` reads back to an equal RigSpec."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    _emit(rig_to_dict(spec), [], lines)
    return "\n".join(lines).strip() + "\n"


def _emit(table: Mapping[str, Any], path: list[str], lines: list[str]) -> None:
    """Scalars of `table` first, then its sub-tables and arrays of tables."""
    subs = {k: v for k, v in table.items() if isinstance(v, dict)}
    arrays = {k: v for k, v in table.items() if _is_table_array(v)}
    if path and (len(subs) + len(arrays) < len(table) or not table):
        lines += ["", f"[{'.'.join(path)}]"]
    for key, value in table.items():
        if key not in subs and key not in arrays:
            lines.append(f"{key} = {_toml(value)}")
    for key, value in subs.items():
        _emit(value, [*path, key], lines)
    for key, items in arrays.items():
        for item in items:
            lines += ["", f"[[{'.'.join([*path, key])}]]"]
            lines += [f"{k} = {_toml(v)}" for k, v in item.items()]


def _is_table_array(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _toml(value: Any) -> str:
    """One TOML value: bool, int, float (exact repr), string, or nested list."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"cannot write a non-finite number {value!r}")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} as TOML")
