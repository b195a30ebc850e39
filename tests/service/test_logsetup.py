"""Log lines: journald priority prefixes under systemd, level names on a terminal."""

from __future__ import annotations

import io
import logging
from collections.abc import Iterator

import pytest

from host.service.logsetup import HANDLER_NAME, format_kv, set_level, setup_logging, under_systemd


@pytest.fixture(autouse=True)
def _restore_root() -> Iterator[None]:
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    for handler in [h for h in root.handlers if h.get_name() == HANDLER_NAME]:
        root.removeHandler(handler)
    root.handlers[:] = handlers
    root.setLevel(level)


def emit(journal: bool, level: str = "debug") -> str:
    stream = io.StringIO()
    setup_logging(level, stream=stream, journal=journal)
    log = logging.getLogger("orbitar.test")
    log.info("link up", extra={"kv": {"device": "/dev/ttyUSB0", "note": "two words"}})
    log.error("lost")
    log.debug("detail")
    return stream.getvalue()


def test_journal_lines_carry_sd_priorities() -> None:
    lines = emit(journal=True).splitlines()
    assert lines == [
        '<6>orbitar.test: link up device=/dev/ttyUSB0 note="two words"',
        "<3>orbitar.test: lost",
        "<7>orbitar.test: detail",
    ]


def test_terminal_lines_carry_level_names() -> None:
    assert emit(journal=False).splitlines()[:2] == [
        'INFO orbitar.test: link up device=/dev/ttyUSB0 note="two words"',
        "ERROR orbitar.test: lost",
    ]


def test_level_filters_and_changes_at_run_time() -> None:
    assert "detail" not in emit(journal=False, level="info")
    set_level("error")
    assert logging.getLogger().level == logging.ERROR
    with pytest.raises(ValueError, match="unknown log level"):
        set_level("loud")


def test_traceback_stays_one_journal_entry() -> None:
    stream = io.StringIO()
    setup_logging("info", stream=stream, journal=True)
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        logging.getLogger("x").exception("failed")
    assert stream.getvalue().count("\n") == 1
    assert "RuntimeError: boom" in stream.getvalue()


def test_systemd_detection() -> None:
    assert under_systemd({"JOURNAL_STREAM": "8:1234"})
    assert under_systemd({"INVOCATION_ID": "abc"})
    assert not under_systemd({})


def test_kv_quoting() -> None:
    assert format_kv({"a": 1, "b": "", "c": 'say "hi"'}) == 'a=1 b="" c="say \\"hi\\""'
