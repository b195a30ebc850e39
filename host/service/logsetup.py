"""Logging to stderr in a form journald keeps: `<N>` priority prefixes under systemd.

A record's `extra={"kv": {...}}` is rendered as trailing `key=value` pairs, so structured facts
(device, seq, rate) stay greppable in the journal and on a terminal alike.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from typing import Any, TextIO

# sd-daemon(3) priorities: the journal reads a leading "<N>" as the syslog level.
SD_PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}
LEVELS = {
    "debug": logging.DEBUG,
    "info": logging.INFO,
    "warning": logging.WARNING,
    "error": logging.ERROR,
    "critical": logging.CRITICAL,
}
HANDLER_NAME = "orbitar-stderr"


def under_systemd(environ: Mapping[str, str] | None = None) -> bool:
    """True when stderr goes to the journal (systemd sets JOURNAL_STREAM and INVOCATION_ID)."""
    env = os.environ if environ is None else environ
    return bool(env.get("JOURNAL_STREAM") or env.get("INVOCATION_ID"))


def format_kv(kv: Mapping[str, Any]) -> str:
    """`key=value` pairs; values with spaces or quotes are quoted so the line parses back."""
    parts = []
    for key, value in kv.items():
        text = str(value)
        if not text or any(c in text for c in ' "=\n'):
            text = '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
        parts.append(f"{key}={text}")
    return " ".join(parts)


class ServiceFormatter(logging.Formatter):
    """`<3>logger: message k=v` for the journal, `ERROR logger: message k=v` for a terminal."""

    def __init__(self, journal: bool) -> None:
        super().__init__()
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        """One line per record (tracebacks folded in with escaped newlines under journald)."""
        text = f"{record.name}: {record.getMessage()}"
        kv = getattr(record, "kv", None)
        if isinstance(kv, Mapping) and kv:
            text += " " + format_kv(kv)
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        if self.journal:
            # The journal splits on newlines, so keep a traceback in one entry.
            prefix = f"<{SD_PRIORITY.get(record.levelno, 6)}>"
            return prefix + text.replace("\n", " | ")
        return f"{record.levelname} {text}"


def parse_level(name: str) -> int:
    """A logging level from its config name; ValueError for an unknown one."""
    try:
        return LEVELS[name.lower()]
    except KeyError:
        raise ValueError(f"unknown log level {name!r} (known: {', '.join(LEVELS)})") from None


def setup_logging(
    level: str = "info", stream: TextIO | None = None, journal: bool | None = None
) -> logging.Handler:
    """Install (or replace) the stderr handler on the root logger and set the level."""
    root = logging.getLogger()
    for old in [h for h in root.handlers if h.get_name() == HANDLER_NAME]:
        root.removeHandler(old)
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.set_name(HANDLER_NAME)
    handler.setFormatter(ServiceFormatter(under_systemd() if journal is None else journal))
    root.addHandler(handler)
    root.setLevel(parse_level(level))
    return handler


def set_level(level: str) -> None:
    """Change the threshold at run time (SIGHUP reload)."""
    logging.getLogger().setLevel(parse_level(level))
