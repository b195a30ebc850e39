"""Build-time constants of the controller and the integer unit conversions of the control path.

The mechanics (encoder, microstepping, sprocket, chain: `Mechanics`, the reference build's
values below) are reported to the host in IDENTIFY.
"""

from __future__ import annotations

from dataclasses import dataclass

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
CHAIN_PITCH_UM = 12_700  # ISO 08B: 254 000 µm of chain per sprocket turn

MAX_FRAME_BYTES = MAX_WIRE_FRAME  # the protocol's limit: one XBee unicast payload
RX_WINDOW = 8
CAPABILITIES = int(Capability.BATCHED_TELEMETRY | Capability.QUIET_CLOCK_PROBES)  # in IDENTIFY
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


@dataclass(frozen=True)
class Mechanics:
    """What the firmware is built for: encoder, microstepping, sprocket and chain.

    The C takes these as build-time constants (one build per drive); the mirror takes them per
    instance so that the simulator can build it for the plant it drives. Reported in IDENTIFY.
    The conversions are exact rational arithmetic on ints, as the C does them.
    """

    encoder_counts_per_rev: int = ENCODER_COUNTS_PER_REV
    steps_per_rev: int = STEPS_PER_REV
    sprocket_teeth: int = SPROCKET_TEETH
    chain_pitch_um: int = CHAIN_PITCH_UM

    def __post_init__(self) -> None:
        fields = (self.encoder_counts_per_rev, self.steps_per_rev)
        if min(*fields, self.sprocket_teeth, self.chain_pitch_um) < 1:
            raise ValueError(f"mechanics must be positive: {self}")

    @property
    def um_per_rev(self) -> int:
        """Chain travel per sprocket turn, µm."""
        return self.sprocket_teeth * self.chain_pitch_um

    def um_to_steps(self, um: int) -> int:
        """Track µm → microsteps, rounded to nearest."""
        return _div_round(um * self.steps_per_rev, self.um_per_rev)

    def steps_to_um(self, steps: int) -> int:
        """Microsteps → track µm, rounded to nearest."""
        return _div_round(steps * self.um_per_rev, self.steps_per_rev)

    def counts_to_um(self, counts: int) -> int:
        """Encoder counts → track µm, rounded to nearest."""
        return _div_round(counts * self.um_per_rev, self.encoder_counts_per_rev)

    def um_to_counts(self, um: int) -> int:
        """Track µm → encoder counts, rounded to nearest."""
        return _div_round(um * self.encoder_counts_per_rev, self.um_per_rev)

    def counts_to_steps(self, counts: int) -> int:
        """Encoder counts → microsteps, rounded to nearest."""
        return _div_round(counts * self.steps_per_rev, self.encoder_counts_per_rev)

    def speed_to_msteps(self, um_s: int) -> int:
        """µm/s → milli-steps per second (the profile's velocity unit), at least 1."""
        return max(1, _div_round(um_s * self.steps_per_rev * MSTEP_PER_STEP, self.um_per_rev))

    def accel_to_msteps_per_tick(self, um_s2: int) -> int:
        """µm/s² → velocity change per tick in milli-steps/s, at least 1."""
        per_s = um_s2 * self.steps_per_rev * MSTEP_PER_STEP
        return max(1, _div_round(per_s, self.um_per_rev * TICK_HZ))


MECHANICS = Mechanics()  # the reference build: the paper's drive


def _div_round(num: int, den: int) -> int:
    """Integer division rounding half away from zero (den > 0), as the C helper does."""
    if num >= 0:
        return (num + den // 2) // den
    return -((-num + den // 2) // den)
