"""Shared vocabulary of the link layer: its errors, its states, its events and its counters."""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field
from typing import TypeVar

from protocol import DropCounters, NakCode, State

log = logging.getLogger("host.link")
E = TypeVar("E", bound=enum.IntEnum)
F = TypeVar("F", bound=enum.IntFlag)
UM_PER_MM = 1000.0  # the wire carries µm, the host works in mm
MAX_UNKNOWN_NOTED = 256  # distinct unknown values logged; beyond that, silence (a flood of noise)
_unknown_noted: set[tuple[str, int]] = set()


def note_unknown(kind: str, value: int) -> None:
    """Log, once per kind and value, that the controller sent a value this host does not know."""
    key = (kind, int(value))
    if key in _unknown_noted or len(_unknown_noted) >= MAX_UNKNOWN_NOTED:
        return
    _unknown_noted.add(key)
    log.warning(
        "controller sent an unknown %s %d (0x%X): shown as a number", kind, int(value), int(value)
    )


def decode_enum(kind: type[E], value: int) -> E | int:
    """A wire integer as its enum member, or (logged once) the plain number: never raises."""
    try:
        return kind(value)
    except ValueError:
        note_unknown(kind.__name__, value)
        return int(value)


def decode_flags(kind: type[F], value: int) -> F:
    """A wire bit field as flags; bits this host does not know are kept and logged once."""
    unknown = int(value) & ~_known_bits(kind)
    if unknown:
        note_unknown(f"{kind.__name__} bit", unknown)
    return kind(value)


def label(value: enum.Enum | int) -> str | int:
    """An enum member's name, or the number itself when the value is not a known member."""
    if isinstance(value, enum.Enum) and value.name is not None:
        return value.name
    return int(value)


def flag_names(flags: enum.IntFlag) -> list[str]:
    """Names of the set known bits, then the unknown bits as one hex number."""
    kind = type(flags)
    names = [m.name for m in kind if m.value and m in flags and m.name is not None]
    unknown = int(flags) & ~_known_bits(kind)
    if unknown:
        names.append(f"0x{unknown:04X}")
    return names


def _known_bits(kind: type[enum.IntFlag]) -> int:
    """Every bit some member of the flag type names."""
    bits = 0
    for member in kind:
        bits |= int(member)
    return bits


class LinkError(Exception):
    """Base of every error the link layer raises to its callers."""


class LinkDown(LinkError):  # noqa: N818 -- the name the API promises
    """The link is not up (or dropped while a command was pending); nothing was queued."""


class CommandTimeout(LinkError):  # noqa: N818
    """A command got no reply after every retransmission."""


class BadIdentity(LinkError):  # noqa: N818
    """IDENTIFY carried constants the host cannot work with (a zero count, pitch or window)."""


class ProtocolMismatch(LinkError):  # noqa: N818
    """The controller speaks another protocol version or schema."""

    def __init__(self, host_version: int, host_hash: int, ctrl_version: int, ctrl_hash: int):
        super().__init__(
            f"protocol mismatch: host speaks version {host_version} schema 0x{host_hash:08X}, "
            f"controller speaks version {ctrl_version} schema 0x{ctrl_hash:08X}"
        )
        self.host_version = host_version
        self.host_hash = host_hash
        self.ctrl_version = ctrl_version
        self.ctrl_hash = ctrl_hash


class OutsideTrack(LinkError):  # noqa: N818
    """A motion that would leave the surveyed open track (or soft limits not yet matching it)."""


class ControllerRejected(LinkError):  # noqa: N818
    """The controller answered NAK: the command changed nothing."""

    def __init__(self, command: str, code: NakCode | int, state: State | int):
        # The session hands over plain numbers for codes and states it does not know.
        if not isinstance(code, NakCode):
            note_unknown("NAK code", code)
        if not isinstance(state, State):
            note_unknown("State", state)
        super().__init__(f"{command} rejected: {label(code)} in state {label(state)}")
        self.command = command
        self.code = code
        self.state = state


class LinkState(enum.Enum):
    """The session as the user sees it."""

    DISCONNECTED = "disconnected"  # never connected, or closed by the user
    CONNECTING = "connecting"  # transport opening or handshake in progress
    UP = "up"  # handshake done: commands accepted
    DOWN = "down"  # lost; a reconnect will follow
    BACKOFF = "backoff"  # waiting before the next connection attempt


class LinkEvent(enum.Enum):
    """What the link tells its listeners about."""

    UP = "up"
    DOWN = "down"
    CONTROLLER_RESET = "controller_reset"  # a new boot id: the controller rebooted
    RESET_SUSPECTED = "reset_suspected"  # uptime or seq ran backwards: re-handshake to check
    HEARTBEAT_TIMEOUT = "heartbeat_timeout"
    COMMAND_LOST = "command_lost"  # a command got no reply: its seq may be a hole


@dataclass
class RttStats:
    """Round-trip times of acknowledged commands (Karn's rule applied), in seconds."""

    srtt_s: float | None = None
    rttvar_s: float | None = None
    min_s: float | None = None
    last_s: float | None = None
    samples: int = 0
    rto_s: float = 0.0


@dataclass
class LinkStats:
    """Counters of one session, kept across reconnects."""

    frames_out: int = 0
    bytes_out: int = 0
    frames_in: int = 0
    bytes_in: int = 0
    drops: DropCounters = field(default_factory=DropCounters)
    commands: int = 0
    retransmits: int = 0
    timeouts: int = 0
    naks: int = 0
    busy_naks: int = 0  # NAK BUSY: ahead of a gap, resent by the retransmission timer
    duplicate_replies: int = 0  # replies to a seq no longer pending (late copies)
    unexpected_replies: int = 0  # reply of the wrong type for its req_seq
    rx_lost: int = 0  # controller frames missing from its seq (telemetry losses)
    rx_out_of_order: int = 0  # controller frames with a seq older than the newest
    clock_probes: int = 0
    clock_replies: int = 0
    clock_pair_firsts: int = 0  # replies that opened a quiet probe pair (not fitted)
    heartbeats_out: int = 0
    heartbeats_in: int = 0
    handshakes: int = 0
    controller_resets: int = 0
    link_downs: int = 0
    rtt: RttStats = field(default_factory=RttStats)
