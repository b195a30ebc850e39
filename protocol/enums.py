"""Enumerations shared by both ends of the link: states, faults, error codes, streams, inputs."""

from __future__ import annotations

import enum


class State(enum.IntEnum):
    """The controller's state machine (PROTOCOL.md, "Controller state machine")."""

    BOOT = 0  # power-up, before the first tick has initialised the drive
    IDLE = 1  # drive enabled, position unknown: only HOME, JOG and head commands move it
    HOMING = 2  # seeking the home switch, then the encoder index
    READY = 3  # homed and standing still: every motion command is accepted
    MOVING = 4  # executing MOVE_TO or JOG
    FAULT = 5  # a latched fault stopped the drive; CLEAR_FAULT returns to IDLE
    ESTOP = 6  # emergency stop latched; only CLEAR_FAULT releases it


class Fault(enum.IntFlag):
    """Latched fault bits reported in STATUS; cleared only by CLEAR_FAULT."""

    NONE = 0  # no fault latched
    WATCHDOG = 0x0001  # no valid frame from the host within the watchdog period
    FOLLOWING_ERROR = 0x0002  # encoder and commanded steps disagree: stall or slip
    HARD_LIMIT = 0x0004  # a limit switch tripped
    SOFT_LIMIT = 0x0008  # the position left the soft-limit window
    HOMING_FAILED = 0x0010  # no home switch or index within the homing travel
    ESTOP = 0x0020  # emergency stop commanded or the e-stop input asserted
    FLASH = 0x0040  # parameter storage corrupt at boot: defaults loaded


class NakCode(enum.IntEnum):
    """Why a command was refused; the refused command changed nothing."""

    UNKNOWN_MESSAGE = 1  # message id not a command this controller knows
    BAD_PAYLOAD = 2  # payload length or text encoding wrong for the id
    OUT_OF_RANGE = 3  # a field is outside its declared range
    BAD_STATE = 4  # not allowed in the current state (NAK carries the state)
    NOT_HOMED = 5  # absolute motion before homing
    BEYOND_LIMIT = 6  # the target lies outside the soft limits
    UNKNOWN_PARAM = 7  # no parameter with that id
    FLASH_ERROR = 8  # persisting the parameters failed
    BUSY = 9  # too far ahead of the command sequence to be held: resend it, same seq, later
    HELLO_REQUIRED = 10  # no HELLO since the controller booted: handshake, then resend
    STALE_SEQ = 11  # behind the command sequence and not a remembered repeat: nothing done


class Capability(enum.IntFlag):
    """Optional features, offered in HELLO and IDENTIFY; one is used only when both set its bit."""

    NONE = 0  # no optional feature; bits are assigned by later revisions (unknown bits ignored)
    BATCHED_TELEMETRY = 0x01  # ENCODER_BATCH, RANGE_BATCH, HEAD_BATCH in place of single samples
    QUIET_CLOCK_PROBES = 0x02  # a CLOCK_SYNC holds telemetry until the next one, at most 40 ms


class Stream(enum.IntEnum):
    """Telemetry streams the host can switch on with STREAM_SET."""

    ENCODER = 0
    STATUS = 1
    RANGE = 2
    HEAD = 3


class Inputs(enum.IntFlag):
    """Digital inputs and position flags carried by ENCODER_SAMPLE and STATUS."""

    NONE = 0  # no input asserted
    HOME = 0x01  # home switch closed
    INDEX = 0x02  # an encoder index pulse was seen since the previous sample
    LIMIT_MIN = 0x04  # lower hard limit switch closed
    LIMIT_MAX = 0x08  # upper hard limit switch closed
    HOMED = 0x10  # position is referenced to home
    ESTOP_IN = 0x20  # e-stop input asserted


class LogLevel(enum.IntEnum):
    """Severity of a LOG message."""

    DEBUG = 0
    INFO = 1
    WARNING = 2
    ERROR = 3
