"""The demo's report: one self-contained HTML page (images inlined) plus results.json."""

from __future__ import annotations

import base64
import html
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

Cell = str | int | float


@dataclass
class _Section:
    """One block of the page: a heading and its HTML body."""

    title: str
    body: str


@dataclass
class Report:
    """Collects tables, figures, snapshots and figures-as-numbers, then writes them."""

    title: str
    sections: list[_Section] = field(default_factory=list)
    results: dict[str, Any] = field(default_factory=dict)

    def add_text(self, title: str, text: str) -> None:
        """A paragraph (plain text, escaped)."""
        paras = "".join(f"<p>{html.escape(p)}</p>" for p in text.split("\n\n") if p.strip())
        self.sections.append(_Section(title, paras))

    def add_table(self, title: str, headers: list[str], rows: list[list[Cell]]) -> None:
        """A table of numbers and words."""
        head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
        body = "".join(
            "<tr>" + "".join(f"<td>{html.escape(_fmt(c))}</td>" for c in row) + "</tr>"
            for row in rows
        )
        self.sections.append(_Section(title, f"<table><tr>{head}</tr>{body}</table>"))

    def add_png(self, title: str, png: bytes, caption: str = "") -> None:
        """An image, inlined as base64 so the page stands alone."""
        data = base64.b64encode(png).decode()
        cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
        self.sections.append(
            _Section(title, f'<figure><img src="data:image/png;base64,{data}">{cap}</figure>')
        )

    def add_image(self, title: str, bgr: NDArray[np.uint8], caption: str = "") -> None:
        """A BGR frame (an overlay snapshot)."""
        import cv2

        ok, buf = cv2.imencode(".png", bgr)
        if not ok:
            raise ValueError(f"could not encode snapshot {title!r}")
        self.add_png(title, buf.tobytes(), caption)

    def add_figure(self, title: str, fig: Any, caption: str = "") -> None:
        """A matplotlib figure."""
        import io

        import matplotlib.pyplot as plt

        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
        plt.close(fig)
        self.add_png(title, buf.getvalue(), caption)

    def write(self, directory: Path) -> Path:
        """Write index.html and results.json into directory; return the page's path."""
        directory.mkdir(parents=True, exist_ok=True)
        page = directory / "index.html"
        page.write_text(self._html(), encoding="utf-8")
        (directory / "results.json").write_text(
            json.dumps(_jsonable(self.results), indent=2, sort_keys=True) + "\n", encoding="utf-8"
        )
        return page

    def _html(self) -> str:
        """The whole page."""
        parts = [f"<h2>{html.escape(s.title)}</h2>{s.body}" for s in self.sections]
        return (
            "<!doctype html><html><head><meta charset='utf-8'>"
            f"<title>{html.escape(self.title)}</title><style>{_CSS}</style></head>"
            f"<body><h1>{html.escape(self.title)}</h1>{''.join(parts)}</body></html>\n"
        )


_CSS = (
    "body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}"
    "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:4px 8px;"
    "text-align:right}th{background:#eee}img{max-width:100%}figcaption{color:#555}"
)


def _fmt(cell: Cell) -> str:
    """Numbers to a readable precision."""
    if isinstance(cell, float):
        if math.isnan(cell):
            return "—"
        return f"{cell:.4g}" if abs(cell) < 1e4 else f"{cell:.0f}"
    return str(cell)


def _jsonable(value: Any) -> Any:
    """numpy scalars and arrays into JSON's types; NaN into null."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return _jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
