"""The rig file: round trips, names the key of every problem, writes atomically with backups."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from host.geometry.transforms import make_T, rot_z
from host.rig import (
    ChainSpec,
    Pose6,
    Provenance,
    RigError,
    RigSpec,
    backups,
    build_camera,
    build_kinematics,
    chain_mismatch,
    dumps_rig,
    load_rig,
    loads_rig,
    save_rig,
    update_rig,
)
from host.rig.store import KEEP_BACKUPS

CUSTOM_OPEN = """
format = 1
name = "test gantry"
[track]
travel_min_mm = 0.0
travel_max_mm = 5570.796326794897
[[track.segments]]
kind = "straight"
length_mm = 3000.0
[[track.segments]]
kind = "arc"
radius_mm = 1500.0
angle_deg = -60.0
[[track.segments]]
kind = "straight"
length_mm = 1000.0
[track.placement]
matrix = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5000], [0, 0, 0, 1]]
[track.home]
value_mm = 80.0
sigma_mm = 1.0
[camera]
width = 1920
height = 1200
"""


def test_default_rig_round_trips_text_and_value() -> None:
    text = dumps_rig(RigSpec())
    again = loads_rig(text)
    assert again == RigSpec()
    assert dumps_rig(again) == text


def test_another_chain_round_trips_and_drives_the_simulated_plant() -> None:
    from hil_sim.rig_scenario import scenario_for_rig

    spec = loads_rig("[track.chain]\nsprocket_teeth = 17\npitch_mm = 15.875\n")
    assert spec.track.chain == ChainSpec(17, 15.875)
    assert loads_rig(dumps_rig(spec)) == spec
    build = scenario_for_rig(spec, seed=1).firmware_build()
    assert (build.sprocket_teeth, build.chain_pitch_um) == (17, 15_875)
    assert chain_mismatch(spec.track.chain, 17, 15.875) == ""
    assert chain_mismatch(spec.track.chain, 20, 12.7) == (
        "sprocket 20 teeth, the rig file's 17; pitch 12.7 mm, the rig file's 15.875 mm"
    )


def test_custom_open_track_round_trips_and_builds() -> None:
    spec = loads_rig(CUSTOM_OPEN)
    rig = build_kinematics(spec)
    assert not rig.track.closed
    assert rig.track.length_mm == pytest.approx(4000.0 + 1500.0 * math.pi / 3)
    assert rig.track.position(0.0)[2] == pytest.approx(5000.0)
    assert build_camera(spec).size == (1920, 1200)
    assert loads_rig(dumps_rig(spec)) == spec


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[camera]\nwidht = 3", "camera.widht: unknown key"),
        ("[camera]\nwidth = 0", "camera.width = 0: out of range"),
        ("[camera.intrinsics]\nfx = -3", "camera.intrinsics.fx = -3: a focal length must be > 0"),
        ("[camera.intrinsics.sigma]\nk1 = -1", "camera.intrinsics.sigma.k1 = -1: out of range"),
        (
            "[head.m_cr]\nmatrix = [[1,0],[0,1]]",
            "head.m_cr.matrix = [[1, 0], [0, 1]]: expected a 4",
        ),
        (
            "[head.m_cr]\nmatrix = [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]",
            "head.m_cr.matrix = [[2, 0, 0, 0]",
        ),
        ("[head]\npan_min_deg = 10\npan_max_deg = 5", "head.pan_min_deg = 10: must be below"),
        ("[track.home]\nvalue_mm = 1e5", "track.home.value_mm = 100000.0: beyond the track"),
        ("[track.marks]\ns_mm = [10, 5]", "track.marks.s_mm[1] = 5.0: must be above"),
        (
            "[track.chain]\nsprocket_teeth = 2.5",
            "track.chain.sprocket_teeth = 2.5: expected an int",
        ),
        ("[track.chain]\npitch_mm = 0", "track.chain.pitch_mm = 0: out of range"),
        ("[track.chain]\nlinks = 3", "track.chain.links: unknown key"),
        (
            '[[track.segments]]\nkind = "arc"\nradius_mm = 0\nangle_deg = 90',
            "track.segments[0]: an arc needs radius_mm > 0",
        ),
        (
            '[track]\nclosed = true\n[[track.segments]]\nkind = "straight"\nlength_mm = 10',
            "track.closed = True: track marked closed",
        ),
        ('[[hall.surfaces]]\nname = "w"\nnormal = [0, 0, 0]', "hall.surfaces[0].normal"),
        ("[rangefinder.mount.provenance]\nviews = -1", "rangefinder.mount.provenance.views = -1"),
        ("format = 7", "format = 7: this Orbitar reads rig format 1"),
        ("[camera", "TOML syntax"),
    ],
)
def test_bad_rig_names_the_key_and_why(text: str, needle: str) -> None:
    with pytest.raises(RigError) as err:
        loads_rig(text)
    assert any(needle in p for p in err.value.problems), err.value.problems


def test_every_problem_is_reported_at_once() -> None:
    with pytest.raises(RigError) as err:
        loads_rig("[camera]\nwidth = 0\nheight = -1\nfoo = 1")
    assert len(err.value.problems) == 3


def test_save_is_atomic_and_keeps_previous_versions(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    assert save_rig(RigSpec(), path) is None
    first = path.read_text()
    backup = save_rig(RigSpec(name="second"), path)
    assert backup is not None
    assert backup.read_text() == first
    assert load_rig(path).name == "second"
    for i in range(KEEP_BACKUPS + 3):
        save_rig(RigSpec(name=f"n{i}"), path)
    assert len(backups(path)) == KEEP_BACKUPS
    assert not list(tmp_path.glob(".*.tmp"))  # no temp file left behind


def test_update_replaces_a_calibrated_block_with_provenance(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    save_rig(RigSpec(), path)
    m_cr = Pose6(
        make_T(rot_z(0.01), [50.0, 47.0, 76.0]),
        (1e-4, 1e-4, 2e-4),
        (0.3, 0.3, 0.5),
        provenance=Provenance.now("calibrate head", 0.21, "px", 24),
    )
    new = update_rig(path, {"head.m_cr": m_cr})
    read = load_rig(path)
    assert read == new
    assert np.allclose(read.head.m_cr.matrix, m_cr.matrix)
    assert read.head.m_cr.provenance.views == 24
    assert read.head.m_cr.provenance.method == "calibrate head"
    assert len(backups(path)) == 1


def test_update_with_an_unknown_block_writes_nothing(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    save_rig(RigSpec(), path)
    before = path.read_text()
    with pytest.raises(RigError, match=r"head\.limits: not a calibrated block"):
        update_rig(path, {"head.limits": 1})
    assert path.read_text() == before
    assert backups(path) == []


def test_unreadable_rig_file_names_the_path(tmp_path: Path) -> None:
    with pytest.raises(RigError, match="cannot read"):
        load_rig(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[camera]\nfps = 0\n")
    with pytest.raises(RigError, match=r"bad\.toml: camera\.fps = 0"):
        load_rig(bad)


def test_rig_default_prints_a_file_rig_check_accepts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from host.cli import main

    assert main(["rig", "default"]) == 0
    path = tmp_path / "rig.toml"
    path.write_text(capsys.readouterr().out)
    assert load_rig(path) == RigSpec()
    assert main(["rig", "check", str(path)]) == 0
    assert "ok (paper runway, 16283.2 mm track, closed)" in capsys.readouterr().out
    path.write_text(CUSTOM_OPEN + "[head]\ntilt_min_deg = 200\n")
    assert main(["rig", "check", str(path)]) == 2
    assert "head.tilt_min_deg = 200: out of range" in capsys.readouterr().err
