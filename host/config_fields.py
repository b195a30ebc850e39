"""Building blocks of the configuration schema: the error type, field specs and value parsers.

`host.config` declares the sections with these; each parser returns the converted value or
raises ValueError with the reason, which the loader reports with the dotted key and the value.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Callable
from dataclasses import field
from typing import Any

SOCKET_MODE_RE = re.compile(r"^0?[0-7]{3}$")
BARE_KEY_RE = re.compile(r"^[A-Za-z0-9_-]+$")

Parser = Callable[[Any], Any]  # returns the converted value or raises ValueError(reason)
SHOWN_MAX_CHARS = 60  # a value quoted in a problem line is cut here (a file may hold megabytes)


class ConfigError(ValueError):
    """A configuration file is wrong; `problems` lists every `key = value: reason` found."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("invalid configuration:\n  " + "\n  ".join(problems))
        self.problems = problems


def shown(value: Any) -> str:
    """`repr(value)` for a problem line, cut to SHOWN_MAX_CHARS."""
    try:
        text = repr(value)
    except RecursionError:
        return f"<{type(value).__name__} nested too deeply to show>"
    return text if len(text) <= SHOWN_MAX_CHARS else text[: SHOWN_MAX_CHARS - 3] + "..."


def toml_key(key: str) -> str:
    """A key as TOML spells it: bare when it may be, else quoted (and cut like a value)."""
    if BARE_KEY_RE.match(key) and len(key) <= SHOWN_MAX_CHARS:
        return key
    return json.dumps(key)[:SHOWN_MAX_CHARS]


def check_text(text: str) -> str:
    """A string without control characters (a NUL in a path or token is a broken file)."""
    for i, char in enumerate(text):
        if ord(char) < 0x20 or 0x7F <= ord(char) < 0xA0:
            raise ValueError(f"control character U+{ord(char):04X} at position {i}")
    return text


def _finite(x: float) -> bool:
    """True for a finite number (an int too large for a float is not)."""
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


_STRING_OR_COMMENT_RE = re.compile(r'"(?:[^"\\]|\\.)*"|\'[^\']*\'|#.*')


def deepest_nesting(text: str) -> tuple[str, int]:
    """The dotted key whose value nests arrays/inline tables deepest, and that depth.

    A rough scan (strings and comments blanked line by line) that only names the culprit when
    tomllib has given up on a file; it never decides whether a file is valid.
    """
    table, key, depth = "", "", 0
    best_key, best_depth = "", 0
    for raw in text.splitlines():
        line = _STRING_OR_COMMENT_RE.sub('""', raw)
        if depth == 0:
            head = line.strip()
            if head.startswith("["):
                table, key = head.strip("[] "), ""
                continue
            if "=" in line:
                name, line = line.split("=", 1)
                key = name.strip()
        for char in line:
            if char in "[{":
                depth += 1
                if depth > best_depth:
                    best_key, best_depth = f"{table}.{key}".strip("."), depth
            elif char in "]}":
                depth = max(0, depth - 1)
    return best_key, best_depth


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
    if not all(_finite(x) for r in rows for x in r):
        raise ValueError("must be finite")
    if [float(x) for x in rows[3]] != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError("the last row of a homogeneous transform must be [0, 0, 0, 1]")
    return tuple(tuple(float(x) for x in r) for r in rows)


def parse_rigid4(value: Any) -> tuple[tuple[float, ...], ...]:
    """A 4×4 transform whose 3×3 block is a rotation within the rounding of printed figures."""
    from host.geometry.head import rotation_problem  # numpy: only when a file sets a matrix

    matrix = parse_matrix4(value)
    problem = rotation_problem(matrix)
    if problem is not None:
        raise ValueError(problem)
    return matrix


def parse_source(value: Any) -> str | int:
    """Camera source: "sim", a device index >= 0, a file path or a URL."""
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise ValueError('expected "sim", a device index, a file path or a URL')
    if isinstance(value, int) and value < 0:
        raise ValueError("a device index must be >= 0")
    if isinstance(value, str) and not value:
        raise ValueError("must not be empty")
    return check_text(value) if isinstance(value, str) else value


def parse_destination(value: Any) -> str:
    """`host:port` with a port in 1..65535."""
    if not isinstance(value, str) or ":" not in value:
        raise ValueError('expected "host:port"')
    check_text(value)
    host, _, port = value.rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError('expected "host:port" with a port in 1..65535')
    return value


def parse_auto_ms(value: Any) -> float | str:
    """ "auto" or milliseconds in [0, 1000]."""
    if value == "auto":
        return "auto"
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not number or not _finite(value) or not 0 <= value <= 1000:
        raise ValueError('expected "auto" or milliseconds in [0, 1000]')
    return float(value)


def parse_vector3(value: Any) -> tuple[float, float, float]:
    """Three numbers."""
    if not isinstance(value, list) or len(value) != 3:
        raise ValueError("expected a list of 3 numbers")
    if any(isinstance(x, bool) or not isinstance(x, int | float) for x in value):
        raise ValueError("expected numbers only")
    if not all(_finite(x) for x in value):
        raise ValueError("must be finite")
    return (float(value[0]), float(value[1]), float(value[2]))


def parse_number(value: Any) -> float:
    """One finite number."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {type(value).__name__}")
    if not _finite(value):
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
