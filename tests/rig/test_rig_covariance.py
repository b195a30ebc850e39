"""The rig file's joint `[covariance]` block: validated, round-tripping, kept fresh by updates."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from host.rig import (
    JointCovariance,
    Pose6,
    Provenance,
    RigError,
    RigSpec,
    Scalar,
    covariance_over,
    dumps_rig,
    joint_covariance,
    loads_rig,
    rig_to_dict,
    with_block,
    with_updates,
)
from host.rig.codec import rig_from_dict

PROV = Provenance("calibrate head (test)", "2026-12-01T00:00:00+00:00", 0.2, "px", 12)


def correlated_rig(rho: float = 0.9) -> RigSpec:
    """M_cr and the track placement with full covariances, their tz correlated by rho."""
    rng = np.random.default_rng(4)
    A = rng.normal(size=(12, 12)) * 1e-3
    cov = A @ A.T + np.diag([1e-7] * 3 + [1.0] * 3 + [1e-7] * 3 + [4.0] * 3)
    cov[5, 11] = cov[11, 5] = rho * np.sqrt(cov[5, 5] * cov[11, 11])
    cov = cov + np.eye(12) * 1e-9  # keep it PD after setting the pair
    base = RigSpec()
    m_cr = Pose6(base.head.m_cr.matrix, covariance=cov[:6, :6], provenance=PROV)
    track = Pose6(base.track.placement.matrix, covariance=cov[6:, 6:], provenance=PROV)
    spec = with_updates(base, {"head.m_cr": m_cr, "track.placement": track})
    joint = joint_covariance(
        {"head.m_cr": cov[:6, :6], "track.placement": cov[6:, 6:]},
        {("head.m_cr", "track.placement"): cov[:6, 6:]},
        PROV,
    )
    return with_updates(spec, {"covariance": joint})


def test_joint_block_and_the_new_inputs_round_trip() -> None:
    spec = correlated_rig()
    spec = dataclasses.replace(
        spec,
        head=dataclasses.replace(spec.head, angle_noise=Scalar(0.0, 5e-5, PROV)),
        camera=dataclasses.replace(spec.camera, clock_sync=Scalar(0.0, 0.12, PROV)),
        track=dataclasses.replace(spec.track, arc_radius_sigma_mm=1.5),
    )
    text = dumps_rig(spec)
    assert "[covariance]" in text
    back = loads_rig(text)
    assert back == spec
    assert dumps_rig(back) == text
    assert back.covariance is not None
    assert back.covariance.names == ("head.m_cr", "track.placement")
    full = covariance_over(back, ["head.m_cr", "track.placement"])
    assert full[5, 11] == pytest.approx(0.9 * np.sqrt(full[5, 5] * full[11, 11]), rel=1e-3)


def test_blocks_not_solved_together_have_no_cross_terms() -> None:
    spec = correlated_rig()
    full = covariance_over(spec, ["camera.intrinsics", "head.m_cr", "workpiece.frame"])
    assert np.all(full[:10, 10:] == 0.0)
    assert np.all(full[10:16, 16:] == 0.0)
    assert np.all(full[10:16, 10:16] == spec.head.m_cr.cov())


def _with_joint(**changes: object) -> dict[str, object]:
    table = rig_to_dict(correlated_rig())
    table["covariance"].update(changes)
    return table


@pytest.mark.parametrize(
    ("changes", "needle"),
    [
        ({"names": ["head.m_cr", "track.nowhere"]}, "name known blocks"),
        ({"names": ["head.m_cr", "head.m_cr"]}, "named twice"),
        ({"names": ["head.m_cr"]}, "expected a 6×6"),
        ({"names": "head.m_cr"}, "expected a list of block names"),
    ],
)
def test_bad_names_or_sizes_are_named(changes: dict[str, object], needle: str) -> None:
    with pytest.raises(RigError) as err:
        rig_from_dict(_with_joint(**changes))
    assert any(p.startswith("covariance") and needle in p for p in err.value.problems)


def test_an_asymmetric_or_indefinite_matrix_is_refused() -> None:
    table = _with_joint()
    M = np.array(table["covariance"]["matrix"])  # type: ignore[index]
    asym = M.copy()
    asym[0, 7] += 1e-3
    with pytest.raises(RigError, match="not symmetric"):
        rig_from_dict(_with_joint(matrix=asym.tolist()))
    indefinite = M.copy()
    c = 2.0 * np.sqrt(M[5, 5] * M[11, 11])  # |ρ| = 2
    indefinite[5, 11] = indefinite[11, 5] = c
    with pytest.raises(RigError, match="positive semi-definite"):
        rig_from_dict(_with_joint(matrix=indefinite.tolist()))


def test_a_block_that_disagrees_with_its_own_covariance_is_refused() -> None:
    table = _with_joint()
    M = np.array(table["covariance"]["matrix"])  # type: ignore[index]
    M[3, 3] *= 2.0
    with pytest.raises(RigError, match=r"head\.m_cr block differs"):
        rig_from_dict(_with_joint(matrix=M.tolist()))


def test_recalibrating_a_covered_block_drops_the_stale_joint_block() -> None:
    spec = correlated_rig()
    moved = Pose6(spec.head.m_cr.matrix, (1e-4,) * 3, (0.5,) * 3, provenance=PROV)
    after = with_updates(spec, {"head.m_cr": moved})
    assert after.covariance is None
    assert loads_rig(dumps_rig(after)) == after
    other = with_updates(spec, {"camera.latency": Scalar(20.0, 1.0, PROV)})
    assert other.covariance == spec.covariance  # not a covered block: kept


def test_with_block_adds_a_block_measured_through_another() -> None:
    spec = correlated_rig()
    B = 0.5 * np.eye(6)  # δp = B δtrack + n: the workpiece measured through the track
    noise = np.eye(6) * 1e-6
    cov_p, joint = with_block(spec, "workpiece.frame", noise, PROV, {"track.placement": B})
    frame = Pose6(spec.workpiece.frame.matrix, covariance=cov_p, provenance=PROV)
    after = with_updates(spec, {"workpiece.frame": frame, "covariance": joint})
    after = loads_rig(dumps_rig(after))  # validated: PSD, blocks agree
    names = ["head.m_cr", "track.placement", "workpiece.frame"]
    full = covariance_over(after, names)
    old = covariance_over(spec, names[:2])
    assert np.allclose(full[:12, :12], old)  # the head run's cross terms are kept
    assert np.allclose(full[12:, 6:12], B @ old[6:, 6:])
    assert np.allclose(full[12:, :6], B @ old[6:, :6])  # through the track, M_cr's too
    assert np.allclose(full[12:, 12:], B @ old[6:, 6:] @ B.T + noise)


def test_joint_covariance_matrix_layout() -> None:
    j = JointCovariance(("camera.intrinsics", "track.placement"), np.eye(16))
    assert j.slices() == {"camera.intrinsics": slice(0, 10), "track.placement": slice(10, 16)}
