"""The commissioning CLI builds the requests the docs describe, and names what is missing."""

from __future__ import annotations

import math
from typing import Any

import pytest

from host import cli
from host.commissioning import cli as ccli
from host.station.parts import BUILTIN_SIDECAR, load_parts


@pytest.fixture
def sent(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, dict[str, Any]]]:
    """The (op, request) pairs `follow` would send to the daemon."""
    calls: list[tuple[str, dict[str, Any]]] = []

    def follow(args: Any, op: str, req: dict[str, Any]) -> int:
        calls.append((op, req))
        return 0

    monkeypatch.setattr(ccli, "follow", follow)
    return calls


def test_the_camera_survey_sends_the_models_feature_points_and_stations(
    sent: list[tuple[str, dict[str, Any]]],
) -> None:
    argv = ["survey", "workpiece", "--method", "camera", "--model-points",
            "builtin:manipulator", "--stations", "400", "950", "1750"]  # fmt: skip
    assert cli.main(argv) == 0
    op, req = sent[0]
    points = [list(p.position_mm) for p in load_parts(BUILTIN_SIDECAR).points]
    assert op == "survey_workpiece"
    assert req == {"method": "camera", "stations_mm": [400.0, 950.0, 1750.0],
                   "model_points_mm": points, "write": True}  # fmt: skip


def test_a_survey_without_what_its_method_needs_says_what_to_give(
    sent: list[tuple[str, dict[str, Any]]], capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["survey", "workpiece", "--method", "camera"]) == 1
    assert "--method camera needs --model-points" in capsys.readouterr().err
    assert cli.main(["survey", "workpiece"]) == 1
    assert "--aims FILE is needed" in capsys.readouterr().err
    assert cli.main(["survey", "workpiece", "--method", "camera", "--model-points", "x.obj"]) == 1
    assert "x.parts.json: cannot read" in capsys.readouterr().err
    assert not sent


def test_the_first_home_survey_takes_the_drawings_sigma(
    sent: list[tuple[str, dict[str, Any]]],
) -> None:
    argv = ["survey", "home", "0", "90", "--rig-sigma", "5.8", "--max-sigma", "10"]
    assert cli.main(argv) == 0
    op, req = sent[0]
    assert op == "survey_home"
    assert req["tilt_rad"] == pytest.approx(math.pi / 2)
    assert (req["rig_sigma_mm"], req["max_sigma_mm"]) == (5.8, 10.0)


def test_the_first_home_surveys_table_shows_the_sigma_it_judged_and_its_parts() -> None:
    from host.commissioning.home_run import home_table
    from host.commissioning.ops import with_rig_sigma

    reading = {"passed": True, "reasons": ["…"], "home_mm": 376.4, "sigma_mm": 1.0,
               "range_mm": 7623.8, "slope": -1.0, "home_before_mm": 450.0}  # fmt: skip
    judged = with_rig_sigma({**reading, "table": home_table(reading)}, 5.8, 10.0)
    rows = {r.rsplit(None, 1)[0].strip(): float(r.rsplit(None, 1)[1])
            for r in judged["table"].splitlines()[2:]}  # fmt: skip
    assert rows["σ (mm)"] == pytest.approx(math.hypot(1.0, 5.8), abs=1e-3)  # as the verdict says
    assert rows["σ of the reading (mm)"] == 1.0
    assert rows["σ of the beam origin (mm)"] == 5.8
    assert f"± {rows['σ (mm)']:.2f} mm" in judged["reasons"][0]


def test_the_progress_line_names_only_the_counts_the_run_reports() -> None:
    import io

    out = io.StringIO()
    view = ccli.ProgressView(out)
    view.show({"phase": "ranging", "view": 1, "of": 1})
    view.show({"phase": "capturing", "view": 3, "of": 20, "accepted": 2, "blurred": 1,
               "not_found": 0})  # fmt: skip
    ranging, capturing = out.getvalue().splitlines()
    assert ranging == "ranging: view 1/1"
    assert capturing.startswith("capturing: view 3/20  kept 2  blurred 1  no board 0")
