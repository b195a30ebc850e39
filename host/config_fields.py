"""Building blocks of the configuration schema: the error type, field specs and value parsers.

`host.config` declares the sections with these; each parser returns the converted value or
raises ValueError with the reason, which the loader reports with the dotted key and the value.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable
from dataclasses import field
from typing import Any

SOCKET_MODE_RE = re.compile(r"^0?[0-7]{3}$")

Parser = Callable[[Any], Any]  # returns the converted value or raises ValueError(reason)


class ConfigError(ValueError):
    """A configuration file is wrong; `problems` lists every `key = value: reason` found."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("invalid configuration:\n  " + "\n  ".join(problems))
        self.problems = problems


def spec(
    default: Any = dataclasses.MISSING,
    *,
    lo: float | None = None,
    hi: float | None = None,
    choices: tuple[Any, ...] | None = None,
    key: str | None = None,
    deg: bool = False,
    parse: Parser | None = None,
    each: bool = False,
    doc: str = "",
) -> Any:
    """A dataclass field with its rule: range, choices, TOML key, degrees, parser, per-item."""
    meta: dict[str, Any] = {"lo": lo, "hi": hi, "choices": choices, "key": key, "deg": deg}
    meta.update(parse=parse, each=each, doc=doc)
    return field(default=default, metadata=meta)


def parse_matrix4(value: Any) -> tuple[tuple[float, ...], ...]:
    """A 4×4 list of numbers whose last row is 0 0 0 1."""
    rows = value if isinstance(value, list) else None
    if rows is None or len(rows) != 4 or any(not isinstance(r, list) or len(r) != 4 for r in rows):
        raise ValueError("expected a 4×4 list of numbers")
    if any(isinstance(x, bool) or not isinstance(x, int | float) for r in rows for x in r):
        raise ValueError("expected numbers only")
    if not all(math.isfinite(x) for r in rows for x in r):
        raise ValueError("must be finite")
    if [float(x) for x in rows[3]] != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError("the last row of a homogeneous transform must be [0, 0, 0, 1]")
    return tuple(tuple(float(x) for x in r) for r in rows)


def parse_source(value: Any) -> str | int:
    """Camera source: "sim", a device index >= 0, a file path or a URL."""
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ValueError('expected "sim", a device index, a file path or a URL')
    if isinstance(value, int) and value < 0:
        raise ValueError("a device index must be >= 0")
    if isinstance(value, str) and not value:
        raise ValueError("must not be empty")
    return value


def parse_destination(value: Any) -> str:
    """`host:port` with a port in 1..65535."""
    if not isinstance(value, str) or ":" not in value:
        raise ValueError('expected "host:port"')
    host, _, port = value.rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError('expected "host:port" with a port in 1..65535')
    return value


def parse_vector3(value: Any) -> tuple[float, float, float]:
    """Three numbers."""
    if not isinstance(value, list) or len(value) != 3:
        raise ValueError("expected a list of 3 numbers")
    if any(isinstance(x, bool) or not isinstance(x, int | float) for x in value):
        raise ValueError("expected numbers only")
    if not all(math.isfinite(x) for x in value):
        raise ValueError("must be finite")
    return (float(value[0]), float(value[1]), float(value[2]))


def parse_number(value: Any) -> float:
    """One finite number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise ValueError("must be finite")
    return float(value)


def parse_mode(value: Any) -> int:
    """An octal permission string such as "0660"."""
    if not isinstance(value, str) or not SOCKET_MODE_RE.match(value):
        raise ValueError('expected an octal mode string such as "0660"')
    return int(value, 8)


def parse_regex(pattern: re.Pattern[str], reason: str) -> Parser:
    """A parser accepting strings that match `pattern`."""

    def parse(value: Any) -> str:
        if not isinstance(value, str) or not pattern.match(value):
            raise ValueError(reason)
        return value

    return parse
