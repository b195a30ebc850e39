"""Regenerate (or check) every file built from the schema.

python -m protocol.generate          # rewrite PROTOCOL.md sections, vectors.json, the C header
python -m protocol.generate --check  # exit 1 and name the stale files, change nothing
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from protocol import SCHEMA_HASH
from protocol.gen_c import generate_header
from protocol.gen_docs import sections, splice
from protocol.gen_vectors import all_vectors

PACKAGE_DIR = Path(__file__).resolve().parent
SPEC_PATH = PACKAGE_DIR / "PROTOCOL.md"
VECTORS_PATH = PACKAGE_DIR / "vectors.json"
HEADER_PATH = PACKAGE_DIR / "c" / "orbitar_protocol.h"


def render() -> dict[Path, str]:
    """Every generated file's expected content, by path."""
    doc = all_vectors(SCHEMA_HASH)
    spec = SPEC_PATH.read_text(encoding="utf-8")
    for name, body in sections(SCHEMA_HASH, doc["vectors"]).items():
        spec = splice(spec, name, body)
    return {
        SPEC_PATH: spec,
        VECTORS_PATH: json.dumps(doc, indent=1, ensure_ascii=False) + "\n",
        HEADER_PATH: generate_header(SCHEMA_HASH),
    }


def stale_files() -> list[Path]:
    """Generated files whose content differs from what the schema produces now."""
    return [
        path
        for path, text in render().items()
        if not path.exists() or path.read_text(encoding="utf-8") != text
    ]


def write_all() -> list[Path]:
    """Rewrite the stale files; return them."""
    changed = []
    for path, text in render().items():
        if not path.exists() or path.read_text(encoding="utf-8") != text:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text, encoding="utf-8")
            changed.append(path)
    return changed


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    ap = argparse.ArgumentParser(prog="python -m protocol.generate", description=__doc__)
    ap.add_argument("--check", action="store_true", help="exit 1 if any file is stale")
    args = ap.parse_args(argv)
    try:
        paths = stale_files() if args.check else write_all()
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    verb = "stale" if args.check else "rewritten"
    for path in paths:
        print(f"{verb}: {_shown(path)}")
    if args.check and paths:
        print("run `python -m protocol.generate` and commit the result", file=sys.stderr)
        return 1
    return 0


def _shown(path: Path) -> str:
    """A path relative to the repository when it lies inside it."""
    try:
        return str(path.relative_to(PACKAGE_DIR.parent))
    except ValueError:
        return str(path)


if __name__ == "__main__":
    sys.exit(main())
