"""Build-time constants of the controller and the integer unit conversions of the control path.

The mechanics (encoder, microstepping, sprocket, chain) are reported to the host in IDENTIFY;
the conversions below are exact rational arithmetic on ints, as the C does them.
"""

from __future__ import annotations

from protocol.enums import Capability
from protocol.schema import MAX_WIRE_FRAME

FW_VERSION = (0 << 16) | (3 << 8) | 0  # major<<16 | minor<<8 | patch

TICK_HZ = 1_000  # control loop rate
TICK_US = 1_000_000 // TICK_HZ
MCU_CLOCK_HZ = 1_000_000  # rate of the micros() timestamp counter

ENCODER_LINES = 1_000
ENCODER_COUNTS_PER_REV = 4 * ENCODER_LINES  # quadrature ×4
FULL_STEPS_PER_REV = 200
MICROSTEPS = 16
STEPS_PER_REV = FULL_STEPS_PER_REV * MICROSTEPS
SPROCKET_TEETH = 20
CHAIN_PITCH_UM = 12_700  # ISO 08B
UM_PER_REV = SPROCKET_TEETH * CHAIN_PITCH_UM  # 254 000 µm of chain per sprocket turn

MAX_FRAME_BYTES = MAX_WIRE_FRAME  # the protocol's limit: one XBee unicast payload
RX_WINDOW = 8
CAPABILITIES = int(Capability.BATCHED_TELEMETRY)  # Capability bits offered in IDENTIFY
REPLY_CACHE_SIZE = 16  # at least RX_WINDOW: duplicates within the window are answered from here
RX_BUFFER_BYTES = 256  # the UART DMA ring
TX_QUEUE_FRAMES = 32
TX_REPLY_RESERVE_FRAMES = 8  # telemetry may not fill the last slots: replies always fit
VELOCITY_FILTER_SHIFT = 3  # measured velocity: IIR with weight 1/8 per tick

# Sub-step fixed point of the profile generator: one step is SUB_PER_STEP units. With the
# velocity kept in milli-steps per second, one 1 ms tick advances the position by exactly
# the velocity's value in sub-steps, so the hot path needs no multiplication.
SUB_PER_STEP = 1_000_000
MSTEP_PER_STEP = 1_000


def um_to_steps(um: int) -> int:
    """Track µm → microsteps, rounded to nearest."""
    return _div_round(um * STEPS_PER_REV, UM_PER_REV)


def steps_to_um(steps: int) -> int:
    """Microsteps → track µm, rounded to nearest."""
    return _div_round(steps * UM_PER_REV, STEPS_PER_REV)


def counts_to_um(counts: int) -> int:
    """Encoder counts → track µm, rounded to nearest."""
    return _div_round(counts * UM_PER_REV, ENCODER_COUNTS_PER_REV)


def um_to_counts(um: int) -> int:
    """Track µm → encoder counts, rounded to nearest."""
    return _div_round(um * ENCODER_COUNTS_PER_REV, UM_PER_REV)


def steps_to_counts(steps: int) -> int:
    """Microsteps → encoder counts, rounded to nearest."""
    return _div_round(steps * ENCODER_COUNTS_PER_REV, STEPS_PER_REV)


def counts_to_steps(counts: int) -> int:
    """Encoder counts → microsteps, rounded to nearest."""
    return _div_round(counts * STEPS_PER_REV, ENCODER_COUNTS_PER_REV)


def speed_to_msteps(um_s: int) -> int:
    """µm/s → milli-steps per second (the profile's velocity unit), at least 1."""
    return max(1, _div_round(um_s * STEPS_PER_REV * MSTEP_PER_STEP, UM_PER_REV))


def accel_to_msteps_per_tick(um_s2: int) -> int:
    """µm/s² → velocity change per tick in milli-steps/s, at least 1."""
    per_s = um_s2 * STEPS_PER_REV * MSTEP_PER_STEP
    return max(1, _div_round(per_s, UM_PER_REV * TICK_HZ))


def _div_round(num: int, den: int) -> int:
    """Integer division rounding half away from zero (den > 0), as the C helper does."""
    if num >= 0:
        return (num + den // 2) // den
    return -((-num + den // 2) // den)
