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
    ProtocolMismatch,
)
from host.link.controller import Controller, Identity, Motion, MotionFailed, SampleSink, Snapshot
from host.link.reconnect import BackoffConfig
from host.link.session import Session, SessionConfig

__all__ = [
    "BackoffConfig",
    "BadIdentity",
    "ClockSync",
    "CommandTimeout",
    "Controller",
    "ControllerRejected",
    "Identity",
    "LinkDown",
    "LinkError",
    "LinkEvent",
    "LinkState",
    "LinkStats",
    "Motion",
    "MotionFailed",
    "ProtocolMismatch",
    "SampleSink",
    "Session",
    "SessionConfig",
    "Snapshot",
]
