"""Shared vocabulary of the link layer: its errors, its states, its events and its counters."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

from protocol import DropCounters, NakCode, State


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


class ControllerRejected(LinkError):  # noqa: N818
    """The controller answered NAK: the command changed nothing."""

    def __init__(self, command: str, code: NakCode, state: State):
        super().__init__(f"{command} rejected: {code.name} in state {state.name}")
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
    duplicate_replies: int = 0  # replies to a seq no longer pending (late copies)
    unexpected_replies: int = 0  # reply of the wrong type for its req_seq
    rx_lost: int = 0  # controller frames missing from its seq (telemetry losses)
    rx_out_of_order: int = 0  # controller frames with a seq older than the newest
    clock_probes: int = 0
    clock_replies: int = 0
    heartbeats_out: int = 0
    heartbeats_in: int = 0
    handshakes: int = 0
    controller_resets: int = 0
    link_downs: int = 0
    rtt: RttStats = field(default_factory=RttStats)
