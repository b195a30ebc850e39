"""`orbitar calibrate head` and `orbitar calibrate check`: the kinematic chain against a board.

Head: the board stays where it was surveyed (T_w_b); the trolley and head move through a pose
set like the intrinsics plan (several stations, the board at the image centre and corners, so
both head axes turn), and each kept view gives the arc length and head angles the host saw with
the board's corners. Robot-world hand-eye (OpenCV, Shah) starts, our least squares on all
corners refines M_cr and the track placement together (host.calibration.handeye), with their
covariances; the track's covariance includes the board survey's.

Check: the installer's acceptance test. From poses not used for calibrating, the board's
corners are predicted through the rig as the rig file now has it (camera, M_cr, track) and
compared with where they are found; the RMS and the worst view are judged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.calibration.handeye import HandEyeResult, HandEyeView, adjoint, calibrate_handeye
from host.commissioning.head_noise import rest_sigma
from host.commissioning.intrinsics_run import CapturedView
from host.commissioning.report import Page, per_view_figure, residual_figure, text_table
from host.experiments.budget import BudgetInputs, overlay_sigma
from host.geometry.camera import CameraModel
from host.geometry.head import Rig
from host.geometry.transforms import FloatArray, R_to_rotvec
from host.rig import Pose6, Provenance, joint_covariance

OUTLIER_FACTOR = 3.0  # a view this many times the median view RMS is dropped...
OUTLIER_FLOOR_PX = 0.15  # ...if it is also above this (a head reading's noise is ~0.07 px)


@dataclass(frozen=True)
class HeadThresholds:
    """What a passing head calibration must reach."""

    max_rms_px: float = 1.0
    min_views: int = 8
    # Each translation σ of M_cr. Along the optical axis it carries the focal length's σ times
    # the board distance (0.1 % of 2.5 m is 2.5 mm), correlated with it so that the overlay
    # does not see it: `calibrate check` judges the overlay itself.
    max_sigma_mm: float = 5.0
    max_sigma_rad: float = 1e-3  # each rotation σ of M_cr

    def text(self) -> str:
        """One line for the verdict."""
        return (
            f"RMS ≤ {self.max_rms_px} px, ≥ {self.min_views} views, σ(M_cr) ≤ "
            f"{self.max_sigma_mm} mm and {self.max_sigma_rad * 1e3:g} mrad per axis"
        )


@dataclass
class HeadOutcome:
    """Verdict, reasons, the hand-eye solution and the views."""

    passed: bool
    reasons: list[str]
    views: list[CapturedView]
    result: HandEyeResult | None = None
    nominal_m_cr: FloatArray | None = None
    nominal_track: FloatArray | None = None

    def rows(self) -> list[list[str | float]]:
        """M_cr and the track placement: nominal, calibrated (rotation vector mrad, mm), σ."""
        res = self.result
        if res is None or self.nominal_m_cr is None or self.nominal_track is None:
            return []
        rows: list[list[str | float]] = []
        blocks = (
            ("M_cr", self.nominal_m_cr, res.M_cr, res.cov_M_cr),
            ("T_w_track", self.nominal_track, res.T_w_track, res.track_covariance),
        )
        for name, nominal, est, cov in blocks:
            d = _local(nominal, est)
            sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
            for i, axis in enumerate(("ωx mrad", "ωy mrad", "ωz mrad", "tx mm", "ty mm", "tz mm")):
                scale = 1e3 if i < 3 else 1.0
                rows.append([f"{name} {axis}", round(d[i] * scale, 4), round(sig[i] * scale, 4)])
        return rows

    def table(self) -> str:
        """Change from nominal and σ, per local axis."""
        return text_table(["parameter (change from nominal)", "change", "sigma"], self.rows())

    def summary(self) -> dict[str, Any]:
        """Plain values for the status op and results.json."""
        out: dict[str, Any] = {
            "passed": self.passed,
            "reasons": self.reasons,
            "views": {
                s: sum(v.status == s for v in self.views) for s in ("ok", "blurred", "not found")
            },
            "table": self.table(),
        }
        if self.result is not None:
            r = self.result
            out.update(
                m_cr=r.M_cr.tolist(), m_cr_covariance=r.cov_M_cr.tolist(),
                T_w_track=r.T_w_track.tolist(),
                T_w_track_covariance=r.track_covariance.tolist(), rms_px=r.rms_px,
                initial_rms_px=r.initial_rms_px,
                per_view_rms_px=r.per_view_rms_px.round(4).tolist(),
            )  # fmt: skip
        return out


def hand_eye_views(views: list[CapturedView], head_sigma_rad: float = 0.0) -> list[HandEyeView]:
    """The kept views as hand-eye observations (arc length and head angles as the host saw them),
    each with the σ of its head angles: the looked-up read noise `head_sigma_rad` scaled to the
    readings its rest's median took."""
    out = []
    for v in views:
        det = v.detection
        if v.status != "ok" or det is None or not np.isfinite([v.s_mm, *v.head_rad]).all():
            continue
        sigma = rest_sigma(head_sigma_rad, len(v.rest_head_rad))
        out.append(HandEyeView(v.s_mm, *v.head_rad, det.object_points, det.image_points, sigma))
    return out


def judge_head(
    views: list[CapturedView], rig: Rig, camera: CameraModel, T_w_b: FloatArray,
    cov_T_w_b: FloatArray,
    limits: HeadThresholds,
    camera_cov: FloatArray | None = None,
    home_sigma_mm: float = 0.0,
    head_sigma_rad: float = 0.0,
) -> HeadOutcome:  # fmt: skip
    """Solve M_cr and the track placement from the kept views, and judge them.

    `home_sigma_mm` (the zero's σ) and `head_sigma_rad` (the head angles' read noise as the
    lookups take them, scaled to each view's rest) widen the result's covariance by what they
    move it (host.calibration.handeye).
    """
    obs = hand_eye_views(views, head_sigma_rad)
    nominal = (rig.T_r_c, rig.track.T_w_track)
    if len(obs) < limits.min_views:
        blurred = sum(v.status == "blurred" for v in views)
        why = (
            f"too few views: {len(obs)} kept of {len(views)} planned ({blurred} blurred), "
            f"need ≥ {limits.min_views}"
        )
        return HeadOutcome(False, [why], views, None, *nominal)
    dropped = 0
    try:
        while True:  # a view whose pose reading was off (still ringing) would bias M_cr
            res = calibrate_handeye(
                obs, rig.track, camera, rig.T_t_r, T_w_b, cov_T_w_b, camera_cov,
                home_sigma_mm=home_sigma_mm,
            )  # fmt: skip
            rms = res.per_view_rms_px
            limit = max(OUTLIER_FACTOR * float(np.median(rms)), OUTLIER_FLOOR_PX)
            keep = [o for o, e in zip(obs, rms, strict=True) if e <= limit]
            if len(keep) == len(obs) or len(keep) < limits.min_views:
                break
            dropped += len(obs) - len(keep)
            for o, e in zip(obs, rms, strict=True):
                if e > limit:  # the page and the views table show it as such
                    used = [v for v in views if v.status == "ok" and v.detection is not None]
                    for v in used:
                        if v.detection is not None and v.detection.image_points is o.image_points:
                            v.status = "outlier"
            obs = keep
    except (ValueError, np.linalg.LinAlgError) as exc:
        return HeadOutcome(False, [f"the solve failed: {exc}"], views, None, *nominal)
    bad = []
    if res.rms_px > limits.max_rms_px:
        bad.append(f"RMS {res.rms_px:.3f} px > {limits.max_rms_px} px")
    sig = np.sqrt(np.clip(np.diag(res.cov_M_cr), 0.0, None))
    if sig[:3].max() > limits.max_sigma_rad:
        bad.append(
            f"σ(M_cr rotation) {sig[:3].max() * 1e3:.2f} mrad > "
            f"{limits.max_sigma_rad * 1e3:g} mrad (turn the head more)"
        )
    if sig[3:].max() > limits.max_sigma_mm:
        bad.append(
            f"σ(M_cr translation) {sig[3:].max():.2f} mm > {limits.max_sigma_mm} mm (more stations)"
        )
    if bad:
        return HeadOutcome(False, bad, views, res, *nominal)
    return HeadOutcome(
        True,
        [
            f"RMS {res.rms_px:.3f} px over {len(obs)} views "
            f"(closed form {res.initial_rms_px:.2f} px)"
            + (f", {dropped} outlier views dropped" if dropped else "")
        ],
        views,
        res,
        *nominal,
    )


def head_rig_update(
    outcome: HeadOutcome, board_surveyed: bool, home_sigma_mm: float = 0.0
) -> dict[str, Any]:
    """`head.m_cr` (and `track.placement` when the board's world pose was surveyed), and the
    joint `covariance` of what was solved together: M_cr, the placement and the intrinsics the
    solve took as known (a focal length off moves the camera along its axis), and the zero
    (`track.home`, σ `home_sigma_mm`) its views' arc lengths were counted from: the placement
    took up its error, and the overlay, whose arc lengths carry the same, sees it cancel."""
    res = outcome.result
    if res is None or not outcome.passed:
        raise ValueError("only a passing calibration is written")
    n = len(res.per_view_rms_px)
    prov = Provenance.now("calibrate head (robot-world hand-eye, refined)", res.rms_px, "px", n)
    updates: dict[str, Any] = {"head.m_cr": _pose6(res.M_cr, res.cov_M_cr, prov)}
    if board_surveyed:
        updates["track.placement"] = _pose6(res.T_w_track, res.track_covariance, prov)
    blocks = {"head.m_cr": res.cov_M_cr}
    cross = {}
    if board_surveyed:
        blocks["track.placement"] = res.track_covariance
        cross[("head.m_cr", "track.placement")] = res.covariance[:6, 6:]
    if res.camera_cov is not None and res.camera_cross is not None:
        blocks["camera.intrinsics"] = res.camera_cov
        cross[("head.m_cr", "camera.intrinsics")] = res.camera_cross[:6]
        if board_surveyed:
            cross[("track.placement", "camera.intrinsics")] = res.camera_cross[6:]
    if res.home_cross is not None and home_sigma_mm > 0.0:
        blocks["track.home"] = np.array([[home_sigma_mm**2]])
        cross[("head.m_cr", "track.home")] = res.home_cross[:6, None]
        if board_surveyed:
            cross[("track.placement", "track.home")] = res.home_cross[6:, None]
    if len(blocks) > 1:
        updates["covariance"] = joint_covariance(blocks, cross, prov)
    return updates


def head_page(outcome: HeadOutcome, limits: HeadThresholds) -> Page:
    """Verdict, the table, per-view RMS and residuals."""
    pg = Page(
        "Head: M_cr and track placement",
        outcome.passed,
        outcome.reasons,
        limits.text(),
        data=outcome.summary(),
    )
    if outcome.result is not None:
        res = outcome.result
        pg.tables.append(
            (
                "Change from nominal (before) to calibrated (after), local axes",
                ["parameter", "change", "σ"],
                outcome.rows(),
            )
        )
        obs = hand_eye_views(outcome.views)
        uv = np.concatenate([o.image_points for o in obs])
        pg.figures.append(
            ("Residuals", residual_figure(uv, np.concatenate(res.residuals_px), (1280, 1024)))
        )
        labels = [v.target.label for v in outcome.views if v.status == "ok"][: len(obs)]
        pg.figures.append(
            ("Per-view RMS", per_view_figure(labels, list(res.per_view_rms_px), limits.max_rms_px))
        )
    return pg


@dataclass
class CheckOutcome:
    """The acceptance test: per-view measured minus predicted corners."""

    passed: bool
    reasons: list[str]
    views: list[CapturedView]
    per_view_rms_px: list[float]
    residuals_px: list[FloatArray]
    rms_px: float
    max_px: float
    predicted_px: float | None = None  # the error budget's σ for these views, detection noise in
    predicted_per_view_px: list[float] | None = None

    def summary(self) -> dict[str, Any]:
        """Plain values."""
        rows: list[list[str | float]] = [
            [v.target.label, round(e, 3)]
            for v, e in zip(self._used(), self.per_view_rms_px, strict=True)
        ]
        return {
            "passed": self.passed, "reasons": self.reasons,
            "rms_px": self.rms_px, "max_px": self.max_px,
            "per_view_rms_px": [round(e, 4) for e in self.per_view_rms_px],
            "table": text_table(["view", "RMS px"], rows),
            "predicted_sigma_px": self.predicted_px,
            "predicted_per_view_px": self.predicted_per_view_px,
        }  # fmt: skip

    def _used(self) -> list[CapturedView]:
        return [v for v in self.views if v.status == "ok" and v.detection is not None]


def check_views(
    views: list[CapturedView], rig: Rig, camera: CameraModel, T_w_b: FloatArray,
    max_rms_px: float, min_views: int = 3,
) -> CheckOutcome:  # fmt: skip
    """Predict each kept view's corners through the rig as known and compare."""
    used = [v for v in views if v.status == "ok" and v.detection is not None]
    per_view, res = [], []
    for v in used:
        det = v.detection
        assert det is not None
        T_c_b = rig.T_c_w(v.s_mm, v.head_rad[0], v.head_rad[1]) @ T_w_b
        uv, _ = camera.project_world(T_c_b, det.object_points)
        r = det.image_points - uv
        res.append(r)
        per_view.append(float(np.sqrt(np.mean(np.sum(r * r, axis=1)))))
    if len(used) < min_views:
        why = f"too few views: {len(used)} kept of {len(views)} planned, need ≥ {min_views}"
        return CheckOutcome(False, [why], views, per_view, res, float("nan"), float("nan"))
    allr = np.concatenate(res)
    rms = float(np.sqrt(np.mean(np.sum(allr * allr, axis=1))))
    worst = float(np.max(np.linalg.norm(allr, axis=1)))
    ok = rms <= max_rms_px
    cmp = "≤" if ok else ">"
    why = (
        f"RMS {rms:.3f} px {cmp} {max_rms_px} px over {len(used)} views "
        f"(worst corner {worst:.2f} px)"
    )
    return CheckOutcome(ok, [why], views, per_view, res, rms, worst)


def with_prediction(
    outcome: CheckOutcome, inputs: BudgetInputs, T_w_b: FloatArray, cov_b: FloatArray
) -> CheckOutcome:
    """The error budget's prediction for the same views, beside the measured RMS.

    The check sees the board the head calibration placed the track with: the survey's error is
    in both and cancels, so the track's covariance here is the rig file's less the board
    survey's share (the hand-eye fit's own), and the board's pose counts as exact.
    """
    T_b_k = np.linalg.inv(T_w_b) @ inputs.rig.track.T_w_track
    Ad = adjoint(np.asarray(np.linalg.inv(T_b_k), dtype=np.float64))
    rel = inputs.track_cov - Ad @ cov_b @ Ad.T
    w, V = np.linalg.eigh((rel + rel.T) / 2)
    rel = (V * np.clip(w, 0.0, None)) @ V.T  # the part left once the shared survey is removed
    board = dataclasses.replace(
        inputs, T_w_p=T_w_b, workpiece_cov=np.zeros((6, 6)), track_cov=rel,
        sigma_head_rad=(0.0, 0.0), speed_mm_s=0.0,
    )  # fmt: skip
    per_view, sq, n = [], 0.0, 0
    for v in outcome._used():
        det = v.detection
        assert det is not None
        b = overlay_sigma(board, v.s_mm, v.head_rad[0], v.head_rad[1], det.object_points)
        sig = float(np.hypot(b.sigma_px, inputs.pixel_noise_px))
        per_view.append(round(sig, 4))
        sq, n = sq + sig * sig * det.count, n + det.count
    if not n:
        return outcome
    pred = float(np.sqrt(sq / n))
    reasons = [*outcome.reasons, f"predicted by the error budget: {pred:.3f} px"]
    return dataclasses.replace(
        outcome, reasons=reasons, predicted_px=pred, predicted_per_view_px=per_view
    )


def check_page(outcome: CheckOutcome, max_rms_px: float) -> Page:
    """The acceptance test's page."""
    pg = Page(
        "Check: measured against predicted",
        outcome.passed,
        outcome.reasons,
        f"RMS ≤ {max_rms_px} px",
        data=outcome.summary(),
    )
    used = outcome._used()
    if used:
        uv = np.concatenate([v.detection.image_points for v in used if v.detection is not None])
        pg.figures.append(
            (
                "Measured minus predicted",
                residual_figure(uv, np.concatenate(outcome.residuals_px), (1280, 1024)),
            )
        )
        pg.figures.append(
            (
                "Per-view RMS",
                per_view_figure(
                    [v.target.label for v in used], outcome.per_view_rms_px, max_rms_px
                ),
            )
        )
    return pg


def _pose6(T: FloatArray, cov: FloatArray, prov: Provenance) -> Pose6:
    """A calibrated transform with its covariance and σ."""
    d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    rad = (float(d[0]), float(d[1]), float(d[2]))
    mm = (float(d[3]), float(d[4]), float(d[5]))
    return Pose6(np.array(T), rad, mm, np.array(cov), prov)


def _local(a: FloatArray, b: FloatArray) -> FloatArray:
    """δ with b = a · exp(δ)."""
    d = np.linalg.inv(a) @ b
    return np.concatenate([R_to_rotvec(d[:3, :3]), d[:3, 3]])
