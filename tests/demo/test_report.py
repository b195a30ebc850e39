"""The report writes a page that stands alone and a results.json that parses."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from host.demo.report import Report


def test_report_writes_html_with_inlined_images_and_json(tmp_path: Path) -> None:
    rep = Report("t")
    rep.add_text("intro", "first\n\nsecond <b>")
    rep.add_table("tab", ["a", "b"], [[1, 2.5], ["x", float("nan")]])
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    rep.add_figure("fig", fig)
    rep.add_image("snap", np.zeros((8, 8, 3), np.uint8))
    rep.results = {"rms": np.float64(0.25), "arr": np.arange(3), "bad": float("nan")}
    page = rep.write(tmp_path / "out")
    text = page.read_text()
    assert text.count("data:image/png;base64,") == 2
    assert "&lt;b&gt;" in text
    assert 'src="http' not in text
    data = json.loads((tmp_path / "out" / "results.json").read_text())
    assert data == {"rms": 0.25, "arr": [0, 1, 2], "bad": None}


def _results(n_static: int, n_moving: int, n_drift: int) -> dict[str, object]:
    """The parts of results.json that say whether frames had a pose."""
    return {
        "static": {"0": {"offset_mm": {"n": n_static}, "frames": 12}},
        "moving": {"samples": n_moving},
        "drift": {"fused_px": {"n": n_drift}},
        "calibration": {"camera.latency_ms": {"estimate": -42.5}},
    }


def test_a_nan_figure_comes_with_the_reason() -> None:
    from host.demo.report_pages import unposed_note

    assert unposed_note(_results(8, 8, 200)) is None
    note = unposed_note(_results(0, 0, 0))
    assert note is not None
    assert "static 0 mm (12 frames), moving, drift" in note
    assert "-42.50 ms" in note


def test_the_commissioning_line_counts_skips_across_the_filters_restarts() -> None:
    from host.demo.report_pages import commissioning_line

    assert commissioning_line({}) == ""
    steps = [
        {"op": "survey_home", "duration_s": 2.0, "chain": {"skips_detected": 0}},
        {"op": "calibrate_intrinsics", "duration_s": 20.0, "chain": {"skips_detected": 2}},
        {"op": "calibrate_head", "duration_s": 1.0, "chain": {"skips_detected": 0}},  # restarted
        {"op": "calibrate_latency", "duration_s": 19.0, "chain": {"skips_detected": 1},
         "clock_error_us": {"median": 265.4, "max": 300.0}},
        {"op": "calibrate_check", "duration_s": 12.0, "chain": {}},  # no filter
    ]  # fmt: skip
    line = commissioning_line({"commissioning": {"steps": steps}})
    assert line.startswith("Commissioning: 5 steps in 54 s")
    assert "(none injected): 3" in line
