"""Every message on the host↔controller link, declared once.

Each class is a row of the message table: its decorator gives id, direction and reply; each
field's annotation gives wire type, unit, range and meaning. The codec, PROTOCOL.md's tables,
the test vectors and the C header are all built from these declarations.
"""

from __future__ import annotations

from typing import Annotated

from protocol.enums import Capability, Fault, Inputs, LogLevel, NakCode, State, Stream
from protocol.schema import (
    I16,
    I32,
    TEXT,
    U8,
    U16,
    U32,
    Direction,
    field,
    message,
    record,
    records,
)

H2C = Direction.TO_CONTROLLER
C2H = Direction.TO_HOST

MAX_SPEED = 2_000_000  # µm/s: 2 m/s, far above any chain trolley
MAX_ACCEL = 10_000_000  # µm/s²
HALF_TURN_URAD = 3_141_593
LOG_TEXT_MAX = 60
_ALL_FAULTS = sum(int(f) for f in Fault)
_ALL_INPUTS = sum(int(f) for f in Inputs)

Seq = Annotated[int, field(U16, "", "sequence number of the command this answers")]
McuTime = Annotated[int, field(U32, "µs", "controller clock at sampling; wraps every 2³² µs")]
_PADDING = (
    "zero; makes the probe as long on the wire as its reply so both directions take equally "
    "long; ignored on receipt"
)


# ---- session -------------------------------------------------------------------------------


@message(0x01, H2C, acked=True, reply="IDENTIFY")
class Hello:
    """Open a session: the controller answers with IDENTIFY whatever the versions."""

    # From version 2 on HELLO and IDENTIFY only grow: fields are appended, never moved, so
    # either side can read the other's version and show why it refuses (PROTOCOL.md §7).
    protocol_version: Annotated[int, field(U8, "", "protocol version the host speaks")]
    schema_hash: Annotated[int, field(U32, "", "CRC-32 of the host's schema text")]
    capabilities: Annotated[
        int,
        field(
            U32, "", "optional features the host supports; unknown bits ignored", enum=Capability
        ),
    ] = 0
    session_id: Annotated[
        int, field(U32, "", "random per host session: a repeat of the same HELLO resets nothing")
    ] = 0


@message(0x02, Direction.BOTH)
class Heartbeat:
    """Liveness in both directions; any valid host frame also feeds the watchdog."""

    uptime_ms: Annotated[int, field(U32, "ms", "sender's uptime, wrapping")]


@message(0x03, H2C, reply="CLOCK_SYNC_REPLY")
class ClockSync:
    """Ask for the controller clock; never retransmitted (a lost probe is just skipped)."""

    # The host assumes the probe takes as long to reach the controller as the reply takes to come
    # back. On a byte-serial link a frame's time on the line grows with its length, so the probe
    # carries padding that makes it exactly as long as CLOCK_SYNC_REPLY (a test in tests/protocol
    # keeps the two equal). Senders send zeros; receivers ignore the values, so the full wire
    # range stays valid on receipt and a later version may give these bytes a meaning.
    token: Annotated[int, field(U32, "", "opaque value echoed in the reply")]
    padding0: Annotated[int, field(U16, "", _PADDING)] = 0
    padding1: Annotated[int, field(U32, "", _PADDING)] = 0
    padding2: Annotated[int, field(U32, "", _PADDING)] = 0


@message(0x04, H2C, acked=True, reply="ACK")
class Reset:
    """Reboot the controller after acknowledging; a new boot id follows."""


# ---- motion --------------------------------------------------------------------------------


@message(0x10, H2C, acked=True, reply="ACK")
class Home:
    """Seek the home switch, then latch the next encoder index as HOME_OFFSET_UM."""

    speed_um_s: Annotated[
        int, field(U32, "µm/s", "seek speed; 0 uses HOME_SPEED_UM_S", hi=MAX_SPEED)
    ]


@message(0x11, H2C, acked=True, reply="ACK")
class MoveTo:
    """Move to an absolute track position along a trapezoidal profile."""

    position_um: Annotated[int, field(I32, "µm", "target arc length from home")]
    speed_um_s: Annotated[int, field(U32, "µm/s", "cruise speed limit", lo=1, hi=MAX_SPEED)]
    accel_um_s2: Annotated[int, field(U32, "µm/s²", "acceleration limit", lo=1, hi=MAX_ACCEL)]


@message(0x12, H2C, acked=True, reply="ACK")
class Jog:
    """Run at a signed velocity until STOP, another motion or a limit."""

    velocity_um_s: Annotated[
        int, field(I32, "µm/s", "signed target velocity", lo=-MAX_SPEED, hi=MAX_SPEED)
    ]
    accel_um_s2: Annotated[int, field(U32, "µm/s²", "acceleration limit", lo=1, hi=MAX_ACCEL)]


@message(0x13, H2C, acked=True, reply="ACK")
class Stop:
    """Controlled stop at STOP_DECEL_UM_S2."""


@message(0x14, H2C, acked=True, reply="ACK")
class Estop:
    """Emergency stop: drive off at once and latch ESTOP until CLEAR_FAULT."""


@message(0x15, H2C, acked=True, reply="ACK")
class ClearFault:
    """Release latched faults and the e-stop; the controller returns to IDLE."""


# ---- head ----------------------------------------------------------------------------------


@message(0x20, H2C, acked=True, reply="ACK")
class HeadSet:
    """Point the pan/tilt head."""

    pan_urad: Annotated[
        int,
        field(I32, "µrad", "pan angle", lo=-HALF_TURN_URAD, hi=HALF_TURN_URAD),
    ]
    tilt_urad: Annotated[
        int,
        field(I32, "µrad", "tilt angle", lo=-HALF_TURN_URAD // 2, hi=HALF_TURN_URAD // 2),
    ]


# ---- parameters and streams ----------------------------------------------------------------


@message(0x30, H2C, acked=True, reply="PARAM_VALUE")
class ParamGet:
    """Read a parameter."""

    param_id: Annotated[int, field(U16, "", "parameter id (PROTOCOL.md, Parameters)")]


@message(0x31, H2C, acked=True, reply="PARAM_VALUE")
class ParamSet:
    """Write a parameter in RAM; the reply carries the value now in force."""

    param_id: Annotated[int, field(U16, "", "parameter id (PROTOCOL.md, Parameters)")]
    value: Annotated[int, field(I32, "param", "new value, in the parameter's unit")]


@message(0x32, H2C, acked=True, reply="ACK")
class ParamPersist:
    """Write all parameters to flash so they survive a reset."""


@message(0x40, H2C, acked=True, reply="ACK")
class StreamSet:
    """Switch a telemetry stream on at a rate, or off with rate 0."""

    stream: Annotated[int, field(U8, "", "which stream", hi=max(Stream), enum=Stream)]
    rate_hz: Annotated[int, field(U16, "Hz", "samples per second; 0 = off", hi=1000)]


# ---- replies -------------------------------------------------------------------------------


@message(0x80, C2H)
class Identify:
    """Answer to HELLO: who the controller is and the constants the host needs."""

    req_seq: Seq
    protocol_version: Annotated[int, field(U8, "", "protocol version the controller speaks")]
    schema_hash: Annotated[int, field(U32, "", "CRC-32 of the controller's schema text")]
    fw_version: Annotated[int, field(U32, "", "firmware version, major<<16 | minor<<8 | patch")]
    boot_id: Annotated[int, field(U32, "", "random at every reset: a change means a reboot")]
    encoder_counts_per_rev: Annotated[int, field(U32, "counts", "quadrature counts per turn")]
    steps_per_rev: Annotated[int, field(U32, "steps", "microsteps per sprocket turn")]
    sprocket_teeth: Annotated[int, field(U8, "", "teeth on the drive sprocket", lo=1)]
    chain_pitch_um: Annotated[int, field(U32, "µm", "nominal chain pitch", lo=1)]
    mcu_clock_hz: Annotated[int, field(U32, "Hz", "rate of the timestamp counter")]
    max_frame: Annotated[int, field(U8, "bytes", "largest wire frame accepted")]
    rx_window: Annotated[int, field(U8, "", "commands the host may have unacknowledged", lo=1)]
    state: Annotated[int, field(U8, "", "current state", hi=max(State), enum=State)]
    capabilities: Annotated[
        int,
        field(
            U32,
            "",
            "optional features the controller supports; unknown bits ignored",
            enum=Capability,
        ),
    ] = 0


@message(0x81, C2H)
class Ack:
    """The command with seq `req_seq` was accepted (or was a duplicate already accepted)."""

    req_seq: Seq
    state: Annotated[int, field(U8, "", "state after the command", hi=max(State), enum=State)]


@message(0x82, C2H)
class Nak:
    """The command with seq `req_seq` was refused and changed nothing."""

    req_seq: Seq
    code: Annotated[int, field(U8, "", "why", lo=1, hi=max(NakCode), enum=NakCode)]
    state: Annotated[int, field(U8, "", "state that refused it", hi=max(State), enum=State)]


@message(0x83, C2H)
class ClockSyncReply:
    """The controller clock when the probe arrived and when this reply was queued for sending."""

    req_seq: Seq
    token: Annotated[int, field(U32, "", "the probe's token")]
    mcu_time_us: Annotated[
        int, field(U32, "µs", "controller clock read as this reply was queued; wraps every 2³² µs")
    ]
    rx_time_us: Annotated[
        int,
        field(
            U32,
            "µs",
            "controller clock when the probe's last byte (its 0x00 delimiter) arrived; "
            "equal to mcu_time_us if the controller cannot stamp arrivals",
        ),
    ]


@message(0x84, C2H)
class ParamValue:
    """A parameter's value in force."""

    req_seq: Seq
    param_id: Annotated[int, field(U16, "", "parameter id")]
    value: Annotated[int, field(I32, "param", "value, in the parameter's unit")]


# ---- telemetry (unacknowledged; gaps in seq count as losses) ------------------------------


@message(0x90, C2H)
class EncoderSample:
    """Sprocket encoder and step generator, sampled together."""

    mcu_time_us: McuTime
    encoder_count: Annotated[int, field(I32, "counts", "quadrature count since home")]
    step_count: Annotated[int, field(I32, "steps", "steps commanded since home")]
    velocity_counts_s: Annotated[int, field(I32, "counts/s", "measured encoder velocity")]
    inputs: Annotated[int, field(U8, "", "input and position flags", hi=_ALL_INPUTS, enum=Inputs)]


@message(0x91, C2H)
class Status:
    """State machine, latched faults and inputs."""

    mcu_time_us: McuTime
    state: Annotated[int, field(U8, "", "current state", hi=max(State), enum=State)]
    faults: Annotated[int, field(U16, "", "latched faults", hi=_ALL_FAULTS, enum=Fault)]
    inputs: Annotated[int, field(U8, "", "input and position flags", hi=_ALL_INPUTS, enum=Inputs)]
    position_um: Annotated[int, field(I32, "µm", "encoder position from home")]
    target_um: Annotated[int, field(I32, "µm", "end of the current motion profile")]
    cmd_seq: Annotated[
        int, field(U16, "", "seq of the last acked command handled in sequence order")
    ] = 0


@message(0x92, C2H)
class RangeSample:
    """Rangefinder distance along its beam."""

    mcu_time_us: McuTime
    distance_um: Annotated[int, field(U32, "µm", "measured distance; 0 when invalid")]
    quality: Annotated[int, field(U8, "", "0 = no echo or out of range, 255 = best")]


@message(0x93, C2H)
class HeadSample:
    """Measured pan/tilt angles."""

    mcu_time_us: McuTime
    pan_urad: Annotated[int, field(I32, "µrad", "measured pan")]
    tilt_urad: Annotated[int, field(I32, "µrad", "measured tilt")]


@message(0x95, C2H)
class RefMark:
    """The trolley passed an absolute reference mark; the count was captured at its edge."""

    # Sent with the ENCODER stream (when it is on) at the tick after the edge. The host knows
    # the marks' surveyed track positions and corrects the drift the sprocket encoder cannot
    # see (chain stretch, tooth skips).

    mcu_time_us: McuTime
    encoder_count: Annotated[
        int, field(I32, "counts", "encoder count captured at the mark's edge, as in ENCODER_SAMPLE")
    ]


@message(0x94, C2H, max_text=LOG_TEXT_MAX)
class Log:
    """Human-readable text from the firmware."""

    level: Annotated[int, field(U8, "", "severity", hi=max(LogLevel), enum=LogLevel)]
    text: Annotated[str, field(TEXT, "", f"UTF-8, at most {LOG_TEXT_MAX} bytes, to frame end")]


# ---- batched telemetry (Capability.BATCHED_TELEMETRY; PROTOCOL.md §14) ----------------------
#
# A batch carries its first sample in full, then one record per further sample holding the
# steps from the sample before it: sample k = sample k−1 + step k (times mod 2³²). A step that
# does not fit its record's type ends the batch; the sample then starts the next one.

TimeStep = Annotated[
    int, field(U16, "µs", "mcu_time_us minus the previous sample's, mod 2³²", lo=1)
]
ENCODER_STEPS_MAX = 6
RANGE_STEPS_MAX = 13
HEAD_STEPS_MAX = 10


@record
class EncoderStep:
    """One further ENCODER_SAMPLE of a batch, as steps from the sample before it."""

    dt_us: TimeStep
    encoder_step: Annotated[int, field(I16, "counts", "encoder_count minus the previous one")]
    step_step: Annotated[int, field(I16, "steps", "step_count minus the previous one")]
    velocity_step: Annotated[
        int, field(I16, "counts/s", "velocity_counts_s minus the previous one")
    ]
    inputs: Annotated[int, field(U8, "", "this sample's inputs", hi=_ALL_INPUTS, enum=Inputs)]


@record
class RangeStep:
    """One further RANGE_SAMPLE of a batch, as steps from the sample before it."""

    dt_us: TimeStep
    distance_step: Annotated[int, field(I16, "µm", "distance_um minus the previous one")]
    quality: Annotated[int, field(U8, "", "this sample's quality")]


@record
class HeadStep:
    """One further HEAD_SAMPLE of a batch, as steps from the sample before it."""

    dt_us: TimeStep
    pan_step: Annotated[int, field(I16, "µrad", "pan_urad minus the previous one")]
    tilt_step: Annotated[int, field(I16, "µrad", "tilt_urad minus the previous one")]


@message(0x96, C2H)
class EncoderBatch:
    """Up to 7 ENCODER_SAMPLEs: the first in full, the others as steps (records to frame end)."""

    mcu_time_us: McuTime
    encoder_count: Annotated[int, field(I32, "counts", "quadrature count since home")]
    step_count: Annotated[int, field(I32, "steps", "steps commanded since home")]
    velocity_counts_s: Annotated[int, field(I32, "counts/s", "measured encoder velocity")]
    inputs: Annotated[int, field(U8, "", "input and position flags", hi=_ALL_INPUTS, enum=Inputs)]
    steps: Annotated[
        tuple[EncoderStep, ...],
        records(EncoderStep, ENCODER_STEPS_MAX, "the further samples, oldest first"),
    ] = ()


@message(0x97, C2H)
class RangeBatch:
    """Up to 14 RANGE_SAMPLEs: the first in full, the others as steps (records to frame end)."""

    mcu_time_us: McuTime
    distance_um: Annotated[int, field(U32, "µm", "measured distance; 0 when invalid")]
    quality: Annotated[int, field(U8, "", "0 = no echo or out of range, 255 = best")]
    steps: Annotated[
        tuple[RangeStep, ...],
        records(RangeStep, RANGE_STEPS_MAX, "the further samples, oldest first"),
    ] = ()


@message(0x98, C2H)
class HeadBatch:
    """Up to 11 HEAD_SAMPLEs: the first in full, the others as steps (records to frame end)."""

    mcu_time_us: McuTime
    pan_urad: Annotated[int, field(I32, "µrad", "measured pan")]
    tilt_urad: Annotated[int, field(I32, "µrad", "measured tilt")]
    steps: Annotated[
        tuple[HeadStep, ...],
        records(HeadStep, HEAD_STEPS_MAX, "the further samples, oldest first"),
    ] = ()
