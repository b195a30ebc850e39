"""An open track's ends, in controller millimetres: what motion may do, and the soft limits.

On an open (not closed) track the surveyed arc length runs over [0, L]; the controller counts
from its zero, which sits at `home_s_mm` on the track. Positions outside are a state to report
and to refuse motion into (homing runs toward negative s first and may end before the start),
never an exception. The controller's own soft limits are kept inside the track: read on every
connect and set to it when they reach beyond it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from host.link.common import UM_PER_MM, ControllerRejected, OutsideTrack
from host.link.session import Session
from protocol import ParamId
from protocol.messages import ParamGet, ParamSet, ParamValue

log = logging.getLogger(__name__)
SOFT_LIMITS = (ParamId.SOFT_LIMIT_MIN_UM, ParamId.SOFT_LIMIT_MAX_UM)


@dataclass(frozen=True)
class TrackWindow:
    """A surveyed open track in controller millimetres: [0, L] minus the track position of home."""

    lo_mm: float
    hi_mm: float

    def where(self, position_mm: float) -> str:
        """ "on", "below_start" or "beyond_end"."""
        if position_mm < self.lo_mm:
            return "below_start"
        return "beyond_end" if position_mm > self.hi_mm else "on"

    def soft_limits_um(self) -> tuple[int, int]:
        """The soft-limit window the controller gets (rounded inwards to whole µm)."""
        return math.ceil(self.lo_mm * UM_PER_MM), math.floor(self.hi_mm * UM_PER_MM)


def check_target(window: TrackWindow, mm: float) -> None:
    """OutsideTrack for a MOVE_TO target off the track."""
    if window.where(mm) != "on":
        raise OutsideTrack(
            f"target {mm:g} mm is outside the surveyed track "
            f"[{window.lo_mm:g}, {window.hi_mm:g}] mm (controller coordinates)"
        )


def check_jog(where: str | None, mm_s: float) -> None:
    """OutsideTrack for a jog further off the track than the trolley already is."""
    if (where == "below_start" and mm_s < 0) or (where == "beyond_end" and mm_s > 0):
        raise OutsideTrack(f"jog {mm_s:g} mm/s refused: the trolley is {where} of the track")


def check_soft_limit(window: TrackWindow, param_id: int, value: int) -> None:
    """OutsideTrack for a soft limit written by hand beyond the track."""
    if param_id not in SOFT_LIMITS:
        return
    lo_um, hi_um = window.soft_limits_um()
    if not lo_um <= value <= hi_um:
        name = ParamId(param_id).name
        raise OutsideTrack(f"{name} = {value} µm: outside the track [{lo_um}, {hi_um}] µm")


async def sync_soft_limits(session: Session, window: TrackWindow) -> str | None:
    """Make the controller's soft limits lie inside the track; None when they do, else why not.

    Sent through the session directly: it runs while a handshake restores the link. A
    controller that refuses (it is moving, say) gets no motion from the host until a later
    attempt succeeds.
    """
    lo_um, hi_um = window.soft_limits_um()
    try:
        cur_lo = await _param(session, ParamGet(ParamId.SOFT_LIMIT_MIN_UM))
        cur_hi = await _param(session, ParamGet(ParamId.SOFT_LIMIT_MAX_UM))
        if lo_um <= cur_lo <= cur_hi <= hi_um:
            return None
        # The controller keeps min <= max after each write: order the two accordingly.
        order = [(ParamId.SOFT_LIMIT_MIN_UM, lo_um), (ParamId.SOFT_LIMIT_MAX_UM, hi_um)]
        if lo_um > cur_hi:
            order.reverse()
        for pid, value in order:
            await _param(session, ParamSet(int(pid), value))
    except ControllerRejected as exc:
        why = f"soft limits could not be set to the track: {exc}"
        log.warning("%s", why)
        return why
    log.info("soft limits set to the track: [%d, %d] µm", lo_um, hi_um)
    return None


async def _param(session: Session, msg: object) -> int:
    """One parameter request; the value in force."""
    reply = (await session.request(msg)).message
    assert isinstance(reply, ParamValue)
    return reply.value
