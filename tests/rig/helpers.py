"""Configurations whose `[rig] path` names a rig file written from text (for the tests)."""

from __future__ import annotations

import atexit
import itertools
import tempfile
from pathlib import Path

from host.config import Config, loads_config

_DIR = tempfile.TemporaryDirectory(prefix="orbitar-rig-tests-")
atexit.register(_DIR.cleanup)
_COUNT = itertools.count()


def rig_file(rig_text: str) -> Path:
    """A fresh rig file holding `rig_text`."""
    path = Path(_DIR.name) / f"rig-{next(_COUNT)}.toml"
    path.write_text(rig_text, encoding="utf-8")
    return path


def rig_config(rig_text: str, config_text: str = "") -> Config:
    """`config_text` plus a [rig] table naming a file that holds `rig_text`."""
    return loads_config(f'{config_text}\n[rig]\npath = "{rig_file(rig_text)}"\n')
