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

    def predicted(s: float) -> float:
        hit = range_at(rig, scene, s, pan, tilt)
        return math.nan if hit is None else hit.distance_mm

    s = s0
    slope = math.nan
    for _ in range(NEWTON_STEPS):
        p = predicted(s)
        slope = (predicted(s + DIFF_MM) - predicted(s - DIFF_MM)) / (2 * DIFF_MM)
        if not (math.isfinite(p) and math.isfinite(slope)):
            return _fail("the beam meets no surveyed surface from here (aim at an end wall)")
        if abs(slope) < MIN_SLOPE:
            return _fail(f"the beam is across the track (∂range/∂s = {slope:.2f} < {MIN_SLOPE})")
        step = (d - p) / slope
        s += step
        if abs(step) < 1e-3:
            break
    sigma = math.hypot(noise_mm / math.sqrt(samples), wall_sigma_mm) / abs(slope)
    home = s - float(position)
    ok = sigma <= MAX_SIGMA_MM
    why = f"home at s = {home:.2f} ± {sigma:.2f} mm (was {io.home_s_mm:.2f})" if ok else (
        f"σ {sigma:.2f} mm > {MAX_SIGMA_MM} mm")  # fmt: skip
    rows: list[list[str | float]] = [
        ["home before (mm)", round(io.home_s_mm, 3)], ["home after (mm)", round(home, 3)],
        ["σ (mm)", round(sigma, 3)], ["reading (mm)", round(d, 2)], ["∂range/∂s", round(slope, 3)],
    ]  # fmt: skip
    return {"passed": ok, "reasons": [why], "home_mm": home, "sigma_mm": sigma, "range_mm": d,
            "slope": slope, "table": text_table(["quantity", "value"], rows)}  # fmt: skip


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
