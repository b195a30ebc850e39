"""`orbitar survey home`: where the controller's zero sits on the track, from a surveyed wall.

With the trolley at rest, the rangefinder is aimed at a surveyed surface with its beam along the
track (an end wall): the reading fixes the arc length s* at which the calibrated rig's beam
meets that surface at the measured distance (Newton in s, the rig's own rangefinder model,
host.geometry.rangefinder). The home is s* less the controller's position. Its σ is the
reading's (noise / √samples, the wall survey's σ) over |∂range/∂s|, so a beam across the track
tells nothing and is refused.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from host.commissioning.frames import RangeTap, wait_ranges
from host.commissioning.motion import RigIO
from host.commissioning.plan import ViewTarget
from host.commissioning.report import Page, text_table
from host.geometry.head import Rig
from host.geometry.rangefinder import RangeScene, range_at
from host.rig import Provenance, Scalar

NEWTON_STEPS = 10
DIFF_MM = 0.1
MIN_SLOPE = 0.5  # |∂range/∂s|: the beam within 60° of the track's direction
MAX_SIGMA_MM = 2.0
RANGE_TIMEOUT_S = 5.0


async def survey_home(
    io: RigIO, tap: RangeTap, rig: Rig, scene: RangeScene, pan: float, tilt: float,
    samples: int, noise_mm: float, wall_sigma_mm: float, progress: dict[str, Any],
) -> dict[str, Any]:  # fmt: skip
    """Aim, read, solve; the result map (passed, reasons, home_mm, sigma_mm, ...)."""
    snap = io.snapshot()
    position = snap.get("position_mm")
    if position is None or snap.get("state") != "READY":
        return _fail(f"the trolley must be homed and at rest (state {snap.get('state')})")
    s0 = float(position) + io.home_s_mm
    progress.update(phase="ranging", view=1, of=1)
    await io.go(ViewTarget(s0, pan, tilt, "home"))
    readings = await wait_ranges(tap, time.monotonic_ns(), samples, RANGE_TIMEOUT_S)
    d = float(np.mean(readings))

    found = locate(rig, scene, s0, pan, tilt, d)
    if isinstance(found, str):
        return _fail(found)
    s, slope = found
    sigma = math.hypot(noise_mm / math.sqrt(samples), wall_sigma_mm) / abs(slope)
    home = s - float(position)
    ok = sigma <= MAX_SIGMA_MM
    why = f"home at s = {home:.2f} ± {sigma:.2f} mm (was {io.home_s_mm:.2f})" if ok else (
        f"σ {sigma:.2f} mm > {MAX_SIGMA_MM} mm")  # fmt: skip
    result = {"passed": ok, "reasons": [why], "home_mm": home, "sigma_mm": sigma, "range_mm": d,
              "slope": slope, "home_before_mm": io.home_s_mm}  # fmt: skip
    return {**result, "table": home_table(result)}


def home_table(result: dict[str, Any]) -> str:
    """The survey's short table; the σ split into its parts when the beam origin's is in."""
    rows: list[list[str | float]] = [
        ["home before (mm)", round(result["home_before_mm"], 3)],
        ["home after (mm)", round(result["home_mm"], 3)],
        ["σ (mm)", round(result["sigma_mm"], 3)],
    ]
    if "rig_sigma_mm" in result:
        rows += [
            ["  σ of the reading (mm)", round(result["reading_sigma_mm"], 3)],
            ["  σ of the beam origin (mm)", round(result["rig_sigma_mm"], 3)],
        ]
    rows += [
        ["reading (mm)", round(result["range_mm"], 2)],
        ["∂range/∂s", round(result["slope"], 3)],
    ]
    return text_table(["quantity", "value"], rows)


def locate(
    rig: Rig, scene: RangeScene, s0: float, pan: float, tilt: float, distance_mm: float
) -> tuple[float, float] | str:
    """The arc length (from s0) at which the rig's beam reads `distance_mm`, and ∂range/∂s
    there; a message instead when the beam meets no surface or runs across the track."""

    def predicted(s: float) -> float:
        hit = range_at(rig, scene, s, pan, tilt)
        return math.nan if hit is None else hit.distance_mm

    s = s0
    slope = math.nan
    for _ in range(NEWTON_STEPS):
        p = predicted(s)
        slope = (predicted(s + DIFF_MM) - predicted(s - DIFF_MM)) / (2 * DIFF_MM)
        if not (math.isfinite(p) and math.isfinite(slope)):
            return "the beam meets no surveyed surface from here (aim at an end wall)"
        if abs(slope) < MIN_SLOPE:
            return f"the beam is across the track (∂range/∂s = {slope:.2f} < {MIN_SLOPE})"
        step = (distance_mm - p) / slope
        s += step
        if abs(step) < 1e-3:
            break
    return s, slope


def home_update(result: dict[str, Any], samples: int) -> dict[str, Any]:
    """`track.home` for the rig file."""
    if not result["passed"]:
        raise ValueError("only a passing survey is written")
    prov = Provenance.now("survey home (rangefinder on a surveyed wall)", None, "", samples)
    return {"track.home": Scalar(float(result["home_mm"]), float(result["sigma_mm"]), prov)}


def home_page(result: dict[str, Any]) -> Page:
    """The report page."""
    pg = Page(
        "Home survey", result["passed"], result["reasons"], f"σ ≤ {MAX_SIGMA_MM} mm", data=result
    )
    if "table" in result:
        pg.preformatted.append(("Result", result["table"]))
    return pg


def _fail(why: str) -> dict[str, Any]:
    return {"passed": False, "reasons": [why]}
