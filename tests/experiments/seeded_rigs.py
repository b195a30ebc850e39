"""Seeded true rigs commissioned offline with the real solvers, for checking the error budget.

Each seed draws a built rig (hil_sim.true_rig, the demo's tolerances) around the demo's rig
description, places the demo's board under the track and surveys it (1 mm, 1 mrad), and then
does what `calibrate intrinsics` and `calibrate head` do, without the daemon: the same plan
(three stations, five image targets), views rendered through the true lens and kinematics by
the synthetic camera and detected, `calibrate_with_rejection`, `calibrate_handeye` with the
intrinsics' covariance, and the rig-file updates those runs write (`rig_update`,
`head_rig_update`), read back through the TOML codec. The host's arc length is off by the home
survey's error (the same in calibration and later). As in the demo, the head run solves the
intrinsics run's own views, and the head reads as the simulator's plant does (`PLANT_HEAD`: it
stands on a count of its encoder and reads it, noise crossing half a count now and then); its
read noise in the rig file is measured from the readings at each rest
(host.commissioning.head_noise), as `calibrate intrinsics` does. `DATASHEET_HEAD` is the
bench's former head: every reading off by the datasheet's σ.

`overlay_errors` is the truth's side: the overlay of the model's points as the commissioned rig
draws them minus where the true rig shows them, at (s, pan, tilt) poses aimed by the host.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hil_sim.camera import SyntheticCamera
from hil_sim.scenario import HeadConfig
from hil_sim.true_rig import true_rig
from host.calibration.board import BoardDetector
from host.calibration.handeye import HandEyeView, adjoint, calibrate_handeye
from host.calibration.intrinsics import calibrate_with_rejection
from host.commissioning import targets_run
from host.commissioning.head_noise import angle_noise_update, rest_sigma
from host.commissioning.head_run import HeadOutcome, head_rig_update
from host.commissioning.intrinsics_run import Outcome, rig_update
from host.commissioning.plan import IMAGE_TARGETS, board_plan
from host.demo.commissioning_phase import (
    BOARD,
    BOARD_SURVEY_SIGMA_MM,
    BOARD_SURVEY_SIGMA_RAD,
    HOME_CLEARANCE_MM,
    WORKPIECE_STATIONS_MM,
    board_stations,
    feature_points,
    place_board,
)
from host.demo.rigs import DemoRigs, paper_demo_rig
from host.experiments.budget import inputs_from_rig, overlay_sigma, visible
from host.geometry.model import manipulator_wireframe
from host.geometry.transforms import (
    FloatArray,
    R_to_rotvec,
    angle_median,
    invert_T,
    make_T,
    rotvec_to_R,
    transform_points,
)
from host.rig import (
    Pose6,
    Provenance,
    RigSpec,
    Scalar,
    build_camera,
    build_kinematics,
    covariance_over,
    dumps_rig,
    loads_rig,
    with_block,
    with_updates,
)
from host.rig.schema import HEAD_ANGLE_SIGMA_RAD

WORKPIECE_SURVEY_RAD = 1e-3  # an independent total-station survey of the workpiece frame
WORKPIECE_SURVEY_MM = 1.0
REST_READINGS = 10  # head readings per rest (about what a board view's wait for its frame sees)


@dataclass(frozen=True)
class SimHead:
    """How the simulated head stands and reads: servo targets and readings on a count of
    `resolution_rad` (0: continuous), readings with `noise_rad` before that rounding."""

    noise_rad: float
    resolution_rad: float = 0.0

    def stand(self, commanded: float) -> float:
        """Where the head truly stands when commanded to an angle."""
        return _round(commanded, self.resolution_rad)

    def read(self, true: float, rng: np.random.Generator) -> float:
        """One reading of the angle it stands at."""
        return _round(true + float(rng.normal(0.0, self.noise_rad)), self.resolution_rad)

    def rest(self, true: FloatArray, rng: np.random.Generator, n: int) -> FloatArray:
        """n readings (n, 2) of pan and tilt standing at `true`."""
        return np.array([[self.read(float(a), rng) for a in true] for _ in range(n)])

    def looked_up(self, true: tuple[float, float], rng: np.random.Generator) -> tuple[float, float]:
        """The angles a frame's pose lookup takes of a standing head: the median of a reading
        and its two neighbours (`AngleBuffer`)."""
        pan, tilt = angle_median(self.rest(np.array(true), rng, 3))
        return float(pan), float(tilt)


def _round(x: float, res: float) -> float:
    return x if res <= 0.0 else round(x / res) * res


PLANT_HEAD = SimHead(HeadConfig().noise_rad, HeadConfig().resolution_rad)  # hil_sim's plant
DATASHEET_HEAD = SimHead(HEAD_ANGLE_SIGMA_RAD)  # every reading off by the datasheet's σ


@dataclass(frozen=True)
class Commissioned:
    """One seeded rig: the truth, the rig file commissioning wrote, and the host's s error."""

    seed: int
    truth: RigSpec
    host: RigSpec
    home_error_mm: float  # host s − true s
    head: SimHead  # how the simulated head stands and reads
    T_w_b_true: FloatArray
    T_w_b_surveyed: FloatArray


def commission(
    seed: int,
    workpiece_surveyed: bool = True,
    projected_noise_px: float | None = None,
    head_noise_modelled: bool = True,
    head: SimHead = PLANT_HEAD,
    reuse_views: bool = True,
    measure_head: bool = True,
    home_sigma_mm: float | None = None,
) -> Commissioned:
    """Draw the rig, calibrate intrinsics then head on rendered views, write the rig file.

    `head`: how the simulated head stands and reads; `measure_head`: the rig file's head noise
    measured from the readings at rest (else the datasheet's); `reuse_views`: the head run
    solves the intrinsics run's views (as the demo), else views taken again; `home_sigma_mm`:
    the zero's σ (default the drawing's 1 mm; the demo's first home survey has ~5 mm, whose
    few draws would then dominate the far side of the loop in a handful of rigs).

    `projected_noise_px`: instead of rendering and detecting, the board's corners projected
    through the truth with independent Gaussian noise of that σ per axis (the solvers' own
    noise model: separates what detection adds from what the covariances claim).
    `head_noise_modelled` False: the hand-eye covariance without the head angles' share."""
    nominal = paper_demo_rig()
    truth = true_rig(nominal, seed)
    rigs = DemoRigs(nominal, truth, nominal, True)
    setup = place_board(rigs, seed)
    rng = np.random.default_rng([seed, 0xB0D6E7])
    # the zero off by its survey's σ (the drawing's, or as given), in the rig file and passed to
    # the head run, whose placement takes it up (and writes the cross terms of it)
    home_sig = nominal.track.home.sigma if home_sigma_mm is None else home_sigma_mm
    home_err = float(rng.normal(0.0, home_sig))
    home = Scalar(nominal.track.home.value, home_sig, Provenance.now("survey home (simulated)"))
    host_rig, host_cam = build_kinematics(nominal), build_camera(nominal)
    true_kin, true_cam = build_kinematics(truth), build_camera(truth)
    s0 = setup.s_mm
    stations, _ = board_stations(rigs, s0, setup.spacing_mm)
    centre = (setup.T_w_b_surveyed @ np.append(BOARD.centre_mm, 1.0))[:3]
    lim = ((nominal.head.pan_min_rad, nominal.head.pan_max_rad),
           (nominal.head.tilt_min_rad, nominal.head.tilt_max_rad))  # fmt: skip
    plan = board_plan(host_rig, host_cam, centre, stations, IMAGE_TARGETS, lim)
    sim = SyntheticCamera(true_cam, seed=seed)
    det = BoardDetector(BOARD)
    T_w_b = setup.placed.T_w_b
    corners = np.asarray(setup.placed.board.getChessboardCorners(), dtype=np.float64).reshape(-1, 3)

    rests: list[FloatArray] = []

    def capture() -> list[HandEyeView]:
        out = []
        for v in plan:
            # the host commands s as it knows it: the trolley stands home_err short of it
            s_true = v.s_mm - home_err
            stood = np.array([head.stand(v.pan_rad), head.stand(v.tilt_rad)])
            T_c_b = invert_T(true_kin.T_w_c(s_true, *stood)) @ T_w_b
            if projected_noise_px is None:
                found = det.detect(sim.render_board(T_c_b, setup.placed.board).image)
                if found is None:
                    continue
                obj, img = found.object_points, found.image_points
            else:
                obj = corners
                img, _ = true_cam.project_world(T_c_b, obj)
                img = img + rng.normal(0.0, projected_noise_px, img.shape)
            rest = head.rest(stood, rng, REST_READINGS)  # waiting for the frame
            rests.append(rest)
            pan, tilt = angle_median(rest)  # as the commissioning runs take a rest's angles
            out.append(HandEyeView(v.s_mm, float(pan), float(tilt), obj, img))
        return out

    intr_views = capture()
    res = calibrate_with_rejection(
        [v.object_points for v in intr_views], [v.image_points for v in intr_views], true_cam.size
    )
    spec = with_updates(nominal, rig_update(Outcome(True, [], [], res, host_cam)))
    spec = with_updates(spec, {"track.home": home})
    if measure_head:
        spec = with_updates(spec, angle_noise_update(rests, len(rests)))
    # each view's head share as `calibrate head` passes it (the rest's median)
    share = rest_sigma(spec.head.angle_noise.sigma, REST_READINGS) if head_noise_modelled else 0.0
    views = [dataclasses.replace(v, head_sigma_rad=share)
             for v in (intr_views if reuse_views else capture())]  # fmt: skip
    cam_cov = np.array(spec.camera.intrinsics.covariance)
    cov_b = np.diag([BOARD_SURVEY_SIGMA_RAD**2] * 3 + [BOARD_SURVEY_SIGMA_MM**2] * 3)
    solved = calibrate_handeye(
        views, host_rig.track, res.camera, host_rig.T_t_r, setup.T_w_b_surveyed, cov_b, cam_cov,
        home_sig,
    )  # fmt: skip
    outcome = HeadOutcome(True, [], [], solved)
    spec = with_updates(spec, head_rig_update(outcome, True, home_sig))
    if workpiece_surveyed:
        spec = with_updates(spec, {"workpiece.frame": surveyed_workpiece(truth, rng)})
    else:  # the workpiece frame exact: the budget of the rig alone
        spec = with_updates(spec, {"workpiece.frame": Pose6(truth.workpiece.frame.matrix)})
    host = loads_rig(dumps_rig(spec))  # as the daemon reads it
    return Commissioned(seed, truth, host, home_err, head, T_w_b, setup.T_w_b_surveyed)


def surveyed_workpiece(truth: RigSpec, rng: np.random.Generator) -> Pose6:
    """The workpiece frame as an independent survey finds it (its σ in the block)."""
    w = rng.normal(0.0, WORKPIECE_SURVEY_RAD, 3)
    t = rng.normal(0.0, WORKPIECE_SURVEY_MM, 3)
    T = truth.workpiece.frame.matrix @ invert_T(make_T(rotvec_to_R(w), t))
    return Pose6(T, (WORKPIECE_SURVEY_RAD,) * 3, (WORKPIECE_SURVEY_MM,) * 3,
                 provenance=Provenance.now("survey (total station)"))  # fmt: skip


def observation_poses(
    c: Commissioned, offsets_mm: Sequence[float], target_p: FloatArray
) -> list[tuple[float, float, float]]:
    """(s, pan, tilt) as the host knows them, aimed by the host at a workpiece point."""
    rig = build_kinematics(c.host)
    start = DemoRigs(c.host, c.truth, c.host, True).start_s_mm()
    target_w = (c.host.workpiece.frame.matrix @ np.append(target_p, 1.0))[:3]
    out = []
    for off in offsets_mm:
        s = start + off
        pan, tilt = rig.aim(s, target_w)
        out.append((s, pan, tilt))
    return out


def overlay_errors(
    c: Commissioned, poses: Sequence[tuple[float, float, float]], points_p: FloatArray,
    rng: np.random.Generator,
) -> list[FloatArray]:  # fmt: skip
    """Per pose, drawn − true pixel (N,2) of each point, NaN rows where either is off-image."""
    host_kin, host_cam = build_kinematics(c.host), build_camera(c.host)
    true_kin, true_cam = build_kinematics(c.truth), build_camera(c.truth)
    T_w_p_host, T_w_p_true = c.host.workpiece.frame.matrix, c.truth.workpiece.frame.matrix
    out = []
    for s, pan, tilt in poses:
        s_true = s - c.home_error_mm
        stood = (c.head.stand(pan), c.head.stand(tilt))
        read = c.head.looked_up(stood, rng)
        drawn, _ = host_cam.project_world(invert_T(host_kin.T_w_c(s, *read)) @ T_w_p_host, points_p)
        true, _ = true_cam.project_world(
            invert_T(true_kin.T_w_c(s_true, *stood)) @ T_w_p_true, points_p
        )
        out.append(drawn - true)
    return out


def replace_workpiece(c: Commissioned, frame: Pose6) -> Commissioned:
    """The same commissioned rig with another workpiece frame in its rig file."""
    return dataclasses.replace(c, host=with_updates(c.host, {"workpiece.frame": frame}))


def board_relative_workpiece(c: Commissioned, rng: np.random.Generator) -> Commissioned:
    """The workpiece surveyed in the board's frame (the same survey set-up as the board's, σ
    WORKPIECE_SURVEY_* relative to it): T_w_p = T_w_b (surveyed) · T_b_p, so the board survey's
    error is in both the workpiece frame and the track placement the head run solved with it.
    The rig file gets the frame and its cross terms with the placement (`with_block`)."""
    T_b_p_true = invert_T(c.T_w_b_true) @ c.truth.workpiece.frame.matrix
    w = rng.normal(0.0, WORKPIECE_SURVEY_RAD, 3)
    t = rng.normal(0.0, WORKPIECE_SURVEY_MM, 3)
    T_b_p = T_b_p_true @ invert_T(make_T(rotvec_to_R(w), t))
    T_w_p = c.T_w_b_surveyed @ T_b_p
    cov_b = np.diag([BOARD_SURVEY_SIGMA_RAD**2] * 3 + [BOARD_SURVEY_SIGMA_MM**2] * 3)
    cov_rel = np.diag([WORKPIECE_SURVEY_RAD**2] * 3 + [WORKPIECE_SURVEY_MM**2] * 3)
    # δp = Ad(T_p_b) δb + δrel; δtrack = Ad(T_k_b) δb + (the fit's own)
    Ad_pb = adjoint(invert_T(T_b_p))
    T_b_k = invert_T(c.T_w_b_surveyed) @ c.host.track.placement.matrix
    Ad_kb = adjoint(invert_T(T_b_k))
    prov = Provenance.now("survey (total station, in the board's frame)")
    shared = {"track.placement": Ad_pb @ cov_b @ Ad_kb.T}
    cov_p, joint = with_block(
        c.host, "workpiece.frame", Ad_pb @ cov_b @ Ad_pb.T + cov_rel, prov, shared=shared
    )
    frame = Pose6(T_w_p, *_sigmas(cov_p), covariance=cov_p, provenance=prov)
    spec = with_updates(c.host, {"workpiece.frame": frame, "covariance": joint})
    return dataclasses.replace(c, host=loads_rig(dumps_rig(spec)))


def camera_surveyed_workpiece(c: Commissioned) -> Commissioned:
    """The workpiece surveyed as `survey workpiece --method camera` does in the demo: targets on
    the model's feature points, seen from the demo's stations (the trolley home_err short of
    where the host commands it, head angles read with their noise) through the true lens,
    found, triangulated through the commissioned rig and written with its cross terms."""
    rigs = DemoRigs(paper_demo_rig(), c.truth, c.host, True)
    features = feature_points(c.truth)
    host_kin, host_cam = build_kinematics(c.host), build_camera(c.host)
    true_kin, true_cam = build_kinematics(c.truth), build_camera(c.truth)
    lo, hi = rigs.travel_mm()
    behind_home = rigs.home_switch_mm() + HOME_CLEARANCE_MM
    stations = [
        min(max(max(rigs.start_s_mm() + d, behind_home), lo + 200.0), hi - 200.0)
        for d in WORKPIECE_STATIONS_MM
    ]
    rough = transform_points(rigs.nominal.workpiece.frame.matrix, features)
    lim = ((c.host.head.pan_min_rad, c.host.head.pan_max_rad),
           (c.host.head.tilt_min_rad, c.host.head.tilt_max_rad))  # fmt: skip
    views = targets_run.plan_views(host_kin, host_cam, rough, stations, lim)
    sim = SyntheticCamera(true_cam, seed=c.seed)
    rng = np.random.default_rng([c.seed, 0x7A6])
    model = manipulator_wireframe()
    T_w_p_true = c.truth.workpiece.frame.matrix
    for v in views:
        t = v.target
        stood = (c.head.stand(t.pan_rad), c.head.stand(t.tilt_rad))
        T_w_c = true_kin.T_w_c(t.s_mm - c.home_error_mm, *stood)
        img = sim.render_scene(T_w_c, model, T_w_p_true, targets_p=features).image
        read = angle_median(c.head.rest(np.array(stood), rng, REST_READINGS))  # as the runs take it
        v.s_mm, v.head_rad = t.s_mm, (float(read[0]), float(read[1]))
        uv, _ = host_cam.project(transform_points(host_kin.T_c_w(t.s_mm, *read), rough))
        for k in v.wanted:
            got = targets_run.find_target(img, uv[k])
            if got is not None:
                v.found[k] = got
    out = targets_run.judge(views, host_kin, host_cam, features, c.host)
    if not out.passed:
        raise RuntimeError(f"seed {c.seed}: the camera survey failed: {out.reasons}")
    spec = with_updates(c.host, targets_run.workpiece_update(out, c.host))
    return dataclasses.replace(c, host=loads_rig(dumps_rig(spec)))


def _sigmas(
    cov: FloatArray,
) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    d = np.sqrt(np.diag(cov))
    return (float(d[0]), float(d[1]), float(d[2])), (float(d[3]), float(d[4]), float(d[5]))


def predicted_and_measured(
    rigs: Sequence[Commissioned], offsets_mm: Sequence[float], points_p: FloatArray,
    without_cross: bool = False,
) -> tuple[FloatArray, FloatArray]:  # fmt: skip
    """(rigs × poses) measured mean-square overlay error and the budget's variance, px², over
    the points the budget sees in the image (NaN where fewer than 3); `without_cross`: the
    budget of the same rig files with their `[covariance]` cross terms removed."""
    meas = np.full((len(rigs), len(offsets_mm)), np.nan)
    pred = np.full_like(meas, np.nan)
    for i, c in enumerate(rigs):
        poses = observation_poses(c, offsets_mm, points_p.mean(axis=0))
        spec = dataclasses.replace(c.host, covariance=None) if without_cross else c.host
        inputs = inputs_from_rig(spec)
        rng = np.random.default_rng([c.seed, 7])
        for j, pose in enumerate(poses):
            pts = visible(inputs, *pose, points_p)
            if len(pts) < 3:
                continue
            e = overlay_errors(c, [pose], pts, rng)[0]
            meas[i, j] = float(np.mean(np.sum(e * e, axis=1)))
            pred[i, j] = overlay_sigma(inputs, *pose, pts).sigma_px ** 2
    return meas, pred


JOINT = ("camera.intrinsics", "head.m_cr", "track.placement")


def joint_nees(c: Commissioned, block_diagonal: bool = False) -> tuple[float, int]:
    """(truth − est)ᵀ Σ⁻¹ (truth − est) of what the head run solved together, and its dof.

    Its mean over rigs should be the dof if the joint covariance is right (the parameters the
    fit holds fixed, zero variance, are left out). The home survey's error, which the placement
    absorbs, is not in the placement's Σ (1 mm against its several mm)."""
    e, t = c.host, c.truth
    d_cam = np.subtract(t.camera.intrinsics.values, e.camera.intrinsics.values)
    d_pose = [_local(e.head.m_cr.matrix, t.head.m_cr.matrix),
              _local(e.track.placement.matrix, t.track.placement.matrix)]  # fmt: skip
    d = np.concatenate([d_cam, *d_pose])
    spec = dataclasses.replace(e, covariance=None) if block_diagonal else e
    S = covariance_over(spec, JOINT)
    keep = np.diag(S) > 0
    S, d = S[np.ix_(keep, keep)], d[keep]
    return float(d @ np.linalg.solve(S, d)), int(keep.sum())


def _local(est: FloatArray, truth: FloatArray) -> FloatArray:
    """δ with truth = est · exp(δ), (ω, t)."""
    D = invert_T(est) @ truth
    return np.concatenate([R_to_rotvec(D[:3, :3]), D[:3, 3]])
