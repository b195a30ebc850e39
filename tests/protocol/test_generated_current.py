"""The generated files (PROTOCOL.md sections, vectors.json, the C header) match the schema."""

from __future__ import annotations

import pytest

from protocol import generate
from protocol.gen_docs import splice


@pytest.mark.parametrize("path", list(generate.render()), ids=lambda p: p.name)
def test_generated_file_is_current(path: object) -> None:
    expected = generate.render()[path]  # type: ignore[index]
    assert path.read_text(encoding="utf-8") == expected, (  # type: ignore[attr-defined]
        f"{path} is stale: run `python -m protocol.generate`"
    )


def test_check_mode_reports_nothing_stale(capsys: pytest.CaptureFixture[str]) -> None:
    assert generate.main(["--check"]) == 0
    assert "stale" not in capsys.readouterr().out


def test_check_mode_detects_a_stale_file(
    tmp_path: object, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from pathlib import Path

    stale = Path(str(tmp_path)) / "orbitar_protocol.h"
    stale.write_text("/* old */\n", encoding="utf-8")
    monkeypatch.setattr(generate, "HEADER_PATH", stale)
    assert generate.main(["--check"]) == 1
    assert "stale" in capsys.readouterr().out
    assert stale.read_text(encoding="utf-8") == "/* old */\n"  # --check changes nothing


def test_splice_keeps_the_prose_and_requires_markers() -> None:
    text = "intro\n<!-- BEGIN GENERATED: x -->\nold\n<!-- END GENERATED: x -->\noutro\n"
    assert splice(text, "x", "new") == text.replace("old", "new")
    with pytest.raises(ValueError, match="'y'"):
        splice(text, "y", "new")
