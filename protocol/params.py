"""The controller's parameter table: ids, units, defaults and ranges (PARAM_GET / PARAM_SET)."""

from __future__ import annotations

import enum
from dataclasses import dataclass


class ParamId(enum.IntEnum):
    """Parameter ids on the wire."""

    WATCHDOG_MS = 1
    MAX_SPEED_UM_S = 2
    MAX_ACCEL_UM_S2 = 3
    STOP_DECEL_UM_S2 = 4
    SOFT_LIMIT_MIN_UM = 5
    SOFT_LIMIT_MAX_UM = 6
    FOLLOWING_ERROR_COUNTS = 7
    HOME_SPEED_UM_S = 8
    HOME_OFFSET_UM = 9
    HOMING_TRAVEL_UM = 10
    ENCODER_BATCH_AGE_MS = 11
    RANGE_BATCH_AGE_MS = 12
    HEAD_BATCH_AGE_MS = 13


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: what it means and what values it takes."""

    id: ParamId
    unit: str
    default: int
    lo: int
    hi: int
    doc: str

    @property
    def name(self) -> str:
        """Name as written in the spec and the C header."""
        return self.id.name


# The paper's runway is 2·(4000 + 1000) + 2π·1000 ≈ 16 283 mm round.
_RUNWAY_UM = 16_283_185

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec(
        ParamId.WATCHDOG_MS,
        "ms",
        500,
        50,
        10_000,
        "host silence that triggers a controlled stop and a WATCHDOG fault",
    ),
    ParamSpec(
        ParamId.MAX_SPEED_UM_S, "µm/s", 500_000, 1_000, 2_000_000, "speed ceiling for every motion"
    ),
    ParamSpec(
        ParamId.MAX_ACCEL_UM_S2,
        "µm/s²",
        500_000,
        1_000,
        5_000_000,
        "acceleration ceiling for every motion",
    ),
    ParamSpec(
        ParamId.STOP_DECEL_UM_S2,
        "µm/s²",
        1_000_000,
        1_000,
        10_000_000,
        "deceleration of STOP, watchdog and limit stops",
    ),
    ParamSpec(
        ParamId.SOFT_LIMIT_MIN_UM,
        "µm",
        0,
        -100_000_000,
        100_000_000,
        "lowest position a motion may reach once homed",
    ),
    ParamSpec(
        ParamId.SOFT_LIMIT_MAX_UM,
        "µm",
        _RUNWAY_UM,
        -100_000_000,
        100_000_000,
        "highest position a motion may reach once homed",
    ),
    ParamSpec(
        ParamId.FOLLOWING_ERROR_COUNTS,
        "counts",
        200,
        4,
        100_000,
        "commanded minus measured position, in encoder counts, that latches a fault",
    ),
    ParamSpec(
        ParamId.HOME_SPEED_UM_S,
        "µm/s",
        50_000,
        1_000,
        500_000,
        "speed while seeking the home switch",
    ),
    ParamSpec(
        ParamId.HOME_OFFSET_UM,
        "µm",
        0,
        -10_000_000,
        10_000_000,
        "position assigned to the home switch's index pulse",
    ),
    ParamSpec(
        ParamId.HOMING_TRAVEL_UM,
        "µm",
        20_000_000,
        1_000,
        100_000_000,
        "travel after which homing gives up with HOMING_FAILED",
    ),
    *(
        ParamSpec(
            pid,
            "ms",
            default,
            0,
            1_000,
            f"with batched telemetry, a {what} batch is sent once its oldest sample is this old "
            "(or when full); 0 sends every sample alone",
        )
        for pid, default, what in (
            (ParamId.ENCODER_BATCH_AGE_MS, 20, "ENCODER"),
            (ParamId.RANGE_BATCH_AGE_MS, 20, "RANGE"),
            (ParamId.HEAD_BATCH_AGE_MS, 50, "HEAD"),
        )
    ),
)

PARAMS_BY_ID: dict[int, ParamSpec] = {int(p.id): p for p in PARAMS}
