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
