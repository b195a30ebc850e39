"""The workpiece's information sidecar: named parts and feature points beside the model file.

For a model `robot.obj` the sidecar is `robot.parts.json` (or the `[ui] parts_path` file):

    {"title": "...",
     "feature_points": [{"name": "P1", "position_mm": [x, y, z], "notes": "..."}, ...],
     "parts": [{"name": "base", "centre_mm": [x, y, z], "points": ["P1"], "notes": "..."}, ...]}

Coordinates are in the workpiece frame p, millimetres. A missing sidecar is no error (the page
then names no parts); a malformed one is a `PartsError` naming the key and the reason.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

BUILTIN_SIDECAR = Path(__file__).with_name("data") / "manipulator.parts.json"
SUFFIX = ".parts.json"


class PartsError(ValueError):
    """A sidecar that cannot be used; the message names the file, the key and why."""


@dataclass(frozen=True)
class FeaturePoint:
    """A named point of the workpiece (the paper's P1…P5)."""

    name: str
    position_mm: tuple[float, float, float]
    notes: str = ""


@dataclass(frozen=True)
class Part:
    """A named piece of the workpiece with its notes and the feature points on it."""

    name: str
    centre_mm: tuple[float, float, float]
    points: tuple[str, ...] = ()
    notes: str = ""


@dataclass(frozen=True)
class Parts:
    """Everything the page names in the view."""

    title: str = ""
    points: tuple[FeaturePoint, ...] = ()
    parts: tuple[Part, ...] = field(default_factory=tuple)

    def to_dict(self) -> dict[str, Any]:
        """Plain values for the page."""
        return {
            "title": self.title,
            "feature_points": [
                {"name": p.name, "position_mm": list(p.position_mm), "notes": p.notes}
                for p in self.points
            ],
            "parts": [
                {
                    "name": p.name,
                    "centre_mm": list(p.centre_mm),
                    "points": list(p.points),
                    "notes": p.notes,
                }
                for p in self.parts
            ],
        }


def sidecar_path(model_path: str, override: str = "") -> Path | None:
    """Where the sidecar of a model lives (the built-in model has one shipped)."""
    if override:
        return Path(override)
    if model_path.startswith("builtin:"):
        return BUILTIN_SIDECAR
    model = Path(model_path)
    return model.with_name(model.stem + SUFFIX)


def load_parts(path: Path | None, required: bool = False) -> Parts:
    """Read a sidecar; an absent file gives empty Parts unless `required`."""
    if path is None or (not path.exists() and not required):
        return Parts()
    try:
        table = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PartsError(f"{path}: cannot read: {exc}") from exc
    try:
        return parse_parts(table)
    except PartsError as exc:
        raise PartsError(f"{path}: {exc}") from exc


def parse_parts(table: Any) -> Parts:
    """Validate a parsed sidecar."""
    if not isinstance(table, dict):
        raise PartsError("expected a JSON object at the top")
    unknown = set(table) - {"title", "feature_points", "parts"}
    if unknown:
        raise PartsError(f"{sorted(unknown)[0]}: unknown key (known: feature_points, parts, title)")
    points = tuple(_point(i, p) for i, p in enumerate(_list(table, "feature_points")))
    names = [p.name for p in points]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise PartsError(f"feature_points[{i}].name = {name!r}: used twice")
    parts = tuple(_part(i, p, set(names)) for i, p in enumerate(_list(table, "parts")))
    return Parts(_text(table, "title", "title"), points, parts)


def _list(table: dict[str, Any], key: str) -> list[Any]:
    """An optional list."""
    value = table.get(key, [])
    if not isinstance(value, list):
        raise PartsError(f"{key}: expected a list")
    return value


def _text(table: dict[str, Any], key: str, where: str, required: bool = False) -> str:
    """An optional (or required) string."""
    value = table.get(key, "")
    if not isinstance(value, str):
        raise PartsError(f"{where}: expected a string, got {value!r}")
    if required and not value:
        raise PartsError(f"{where}: required")
    return value


def _vector(table: dict[str, Any], key: str, where: str) -> tuple[float, float, float]:
    """Three finite numbers."""
    value = table.get(key)
    ok = isinstance(value, list) and len(value) == 3
    if ok and isinstance(value, list):
        ok = all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            for v in value
        )
    if not ok or not isinstance(value, list):
        raise PartsError(f"{where} = {value!r}: expected [x, y, z] in mm")
    return (float(value[0]), float(value[1]), float(value[2]))


def _point(index: int, item: Any) -> FeaturePoint:
    """One feature point."""
    where = f"feature_points[{index}]"
    if not isinstance(item, dict):
        raise PartsError(f"{where}: expected an object")
    return FeaturePoint(
        _text(item, "name", f"{where}.name", required=True),
        _vector(item, "position_mm", f"{where}.position_mm"),
        _text(item, "notes", f"{where}.notes"),
    )


def _part(index: int, item: Any, point_names: set[str]) -> Part:
    """One part; its points must be listed feature points."""
    where = f"parts[{index}]"
    if not isinstance(item, dict):
        raise PartsError(f"{where}: expected an object")
    points = item.get("points", [])
    if not isinstance(points, list) or not all(isinstance(p, str) for p in points):
        raise PartsError(f"{where}.points: expected a list of feature point names")
    for p in points:
        if p not in point_names:
            raise PartsError(f"{where}.points: {p!r} is not a listed feature point")
    return Part(
        _text(item, "name", f"{where}.name", required=True),
        _vector(item, "centre_mm", f"{where}.centre_mm"),
        tuple(points),
        _text(item, "notes", f"{where}.notes"),
    )
