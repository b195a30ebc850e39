"""The commissioning report: one directory per run with an HTML page, its figures and JSON.

Every command ends here: its verdict against the stated threshold, a short table (the same the
terminal shows), per-view errors, coverage and residual plots, and before (nominal) beside after
(calibrated). `results.json` holds the same numbers for tools. Figures are matplotlib PNGs.
"""

from __future__ import annotations

import datetime
import html
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from host.geometry.transforms import FloatArray

Row = Sequence[str | int | float]


@dataclass
class Page:
    """What a report page shows."""

    title: str
    verdict: bool
    reasons: list[str]
    threshold: str
    tables: list[tuple[str, Sequence[str], Sequence[Row]]] = field(default_factory=list)
    figures: list[tuple[str, Any]] = field(default_factory=list)  # caption, matplotlib figure
    preformatted: list[tuple[str, str]] = field(default_factory=list)  # caption, text
    data: dict[str, Any] = field(default_factory=dict)


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend, imported at the first figure: the daemon imports
    this module at start, and pyplot was ~40 % of its start-up imports."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def run_dir(root: Path, kind: str) -> Path:
    """A fresh directory `root/YYYYmmdd-HHMMSS-kind` (suffixed if it exists)."""
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%d-%H%M%S")
    base = root / f"{stamp}-{kind}"
    out, n = base, 1
    while out.exists():
        n += 1
        out = base.with_name(f"{base.name}-{n}")
    out.mkdir(parents=True)
    return out


def write_page(directory: Path, page: Page) -> Path:
    """Write index.html, figures and results.json; the page's path."""
    parts = [
        f"<!doctype html><meta charset='utf-8'><title>{html.escape(page.title)}</title>",
        "<style>body{font-family:sans-serif;max-width:70em;margin:2em auto}"
        "table{border-collapse:collapse}"
        "td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}"
        ".pass{color:#070}.fail{color:#b00}</style>",
        f"<h1>{html.escape(page.title)}</h1>",
        _verdict_html(page),
    ]
    for caption, text in page.preformatted:
        parts.append(f"<h2>{html.escape(caption)}</h2><pre>{html.escape(text)}</pre>")
    for caption, header, rows in page.tables:
        parts.append(f"<h2>{html.escape(caption)}</h2>{_table_html(header, rows)}")
    for i, (caption, fig) in enumerate(page.figures):
        name = f"figure{i + 1}.png"
        fig.savefig(directory / name, dpi=90, bbox_inches="tight")
        pyplot().close(fig)
        parts.append(
            f"<h2>{html.escape(caption)}</h2><img src='{name}' alt='{html.escape(caption)}'>"
        )
    path = directory / "index.html"
    path.write_text("\n".join(parts) + "\n", encoding="utf-8")
    (directory / "results.json").write_text(
        json.dumps(page.data, indent=2, default=_plain), encoding="utf-8"
    )
    return path


def text_table(header: Sequence[str], rows: Sequence[Row]) -> str:
    """A fixed-width table for the terminal."""
    cells = [[str(h) for h in header]] + [[_fmt(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def residual_figure(points_uv: FloatArray, residuals_px: FloatArray, size: tuple[int, int]) -> Any:
    """Residual vectors over the image (scaled up) and their scatter."""
    fig, (a, b) = pyplot().subplots(1, 2, figsize=(11, 4.2))
    if len(points_uv):
        scale = 0.15 * size[0] / max(float(abs(residuals_px).max()), 1e-9)
        du, dv = residuals_px[:, 0] * scale, residuals_px[:, 1] * scale
        a.quiver(points_uv[:, 0], points_uv[:, 1], du, dv, angles="xy", scale_units="xy", scale=1)
        b.scatter(residuals_px[:, 0], residuals_px[:, 1], s=3, alpha=0.5)
    a.set_xlim(0, size[0])
    a.set_ylim(size[1], 0)
    a.set_title("residuals over the image (magnified)")
    b.set_aspect("equal", adjustable="datalim")
    b.set_xlabel("du (px)")
    b.set_ylabel("dv (px)")
    b.set_title("residual scatter")
    return fig


def per_view_figure(labels: Sequence[str], errors_px: Sequence[float], limit_px: float) -> Any:
    """A bar per view with the threshold drawn."""
    fig, ax = pyplot().subplots(figsize=(11, 3.2))
    ax.bar(range(len(errors_px)), errors_px)
    ax.axhline(limit_px, color="r", linestyle="--", label=f"threshold {limit_px} px")
    ax.set_xticks(range(len(labels)))
    ax.set_xticklabels(labels, rotation=90, fontsize=6)
    ax.set_ylabel("RMS (px)")
    ax.legend()
    return fig


def _verdict_html(page: Page) -> str:
    cls, word = ("pass", "PASS") if page.verdict else ("fail", "FAIL")
    reasons = "".join(f"<li>{html.escape(r)}</li>" for r in page.reasons)
    limit = html.escape(page.threshold)
    return f"<p class='{cls}'><b>{word}</b> (threshold: {limit})</p><ul>{reasons}</ul>"


def _table_html(header: Sequence[str], rows: Sequence[Row]) -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(_fmt(c))}</td>" for c in r) + "</tr>" for r in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _fmt(c: str | int | float) -> str:
    if isinstance(c, float):
        return f"{c:.6g}"
    return str(c)


def _plain(o: Any) -> Any:
    """numpy values and arrays as JSON."""
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
