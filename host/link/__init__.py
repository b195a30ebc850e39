"""The host end of the controller link: session, clock sync, reconnection and the controller API."""

from host.link.clocksync import ClockSync
from host.link.common import (
    BadIdentity,
    CommandTimeout,
    ControllerRejected,
    LinkDown,
    LinkError,
    LinkEvent,
    LinkState,
    LinkStats,
    OutsideTrack,
    ProtocolMismatch,
)
from host.link.controller import Controller, Motion, MotionFailed
from host.link.limits import TrackWindow
from host.link.reconnect import BackoffConfig
from host.link.samples import SampleSink
from host.link.session import Session, SessionConfig
from host.link.snapshot import ControllerChange, Identity, Snapshot

__all__ = [
    "BackoffConfig",
    "BadIdentity",
    "ClockSync",
    "CommandTimeout",
    "Controller",
    "ControllerChange",
    "ControllerRejected",
    "Identity",
    "LinkDown",
    "LinkError",
    "LinkEvent",
    "LinkState",
    "LinkStats",
    "Motion",
    "MotionFailed",
    "OutsideTrack",
    "ProtocolMismatch",
    "SampleSink",
    "Session",
    "SessionConfig",
    "Snapshot",
    "TrackWindow",
]
