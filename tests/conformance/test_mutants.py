"""Mutant firmware: break one rule of the mirror at a time and show the suite catches it."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from firmware import commands, controller
from firmware.link import ReplyCache, TxQueue
from host.conformance.base import Options
from host.conformance.run import report, run_suite
from protocol import Flag, State
from protocol.enums import Capability
from protocol.messages import Status
from tests.conformance.conftest import FAST_HOME_UM_S, mirror_over


def _reorder(monkeypatch: pytest.MonkeyPatch) -> None:
    """Run a command ahead of a gap at once instead of holding it (the issue's 10 in 60)."""
    original = commands.handle

    def handle(fw: Any, seq: int, flags: int, msg_id: int, raw: bytes, *rest: int) -> None:
        ahead = (seq - fw.next_cmd_seq) % 0x1_0000
        if flags & Flag.ACK_REQUESTED and 0 < ahead < 0x8000 and fw.hello_seen:
            fw.next_cmd_seq = seq
        original(fw, seq, flags, msg_id, raw, *rest)

    monkeypatch.setattr(commands, "handle", handle)


def _skip_status(monkeypatch: pytest.MonkeyPatch) -> None:
    """Send no STATUS on a state change (the streams-off gap the issue found)."""
    original = TxQueue.send

    def send(self: TxQueue, msg: object, reply: bool = False, *args: Any, **kw: Any) -> bool:
        if isinstance(msg, Status) and reply:
            return False
        return original(self, msg, reply, *args, **kw)

    monkeypatch.setattr(TxQueue, "send", send)


def _forget_duplicates(monkeypatch: pytest.MonkeyPatch) -> None:
    """Remember no reply: a retransmission finds nothing."""
    monkeypatch.setattr(ReplyCache, "lookup", lambda self, seq: None)


def _watchdog_only_in_motion(monkeypatch: pytest.MonkeyPatch) -> None:
    """The watchdog as the mirror had it: only from MOVING and HOMING."""
    monkeypatch.setattr(controller, "_WATCHDOG_STATES", (State.MOVING, State.HOMING))


def _batch_unasked(monkeypatch: pytest.MonkeyPatch) -> None:
    """Batch whenever the controller can, whatever the host offered in HELLO."""

    def start_session(self: Any, host_capabilities: int) -> None:
        self._flush_batches()
        self.batching = bool(self.capabilities & Capability.BATCHED_TELEMETRY)

    monkeypatch.setattr(controller.Firmware, "start_session", start_session)


def _batch_without_age(monkeypatch: pytest.MonkeyPatch) -> None:
    """Send a batch only when it is full (or a step does not fit): the age is never checked."""
    monkeypatch.setattr(controller.Firmware, "_send_due_batches", lambda self: None)


def _batch_at_age_zero(monkeypatch: pytest.MonkeyPatch) -> None:
    """Age 0 still batches (one sample a batch) instead of sending single samples."""
    original = controller.Firmware._batch_age_us
    monkeypatch.setattr(
        controller.Firmware, "_batch_age_us", lambda self, stream: max(1, original(self, stream))
    )


def _drop_batch_when_off(monkeypatch: pytest.MonkeyPatch) -> None:
    """Switching a stream off discards the samples waiting in its batch."""
    original = controller.Firmware.set_stream

    def set_stream(self: Any, stream: int, rate_hz: int) -> None:
        if rate_hz == 0 and stream in self.batchers:
            self.batchers[stream].clear()
        original(self, stream, rate_hz)

    monkeypatch.setattr(controller.Firmware, "set_stream", set_stream)


MUTANTS: list[tuple[str, Callable[[pytest.MonkeyPatch], None], str]] = [
    ("reorder", _reorder, "R-ORDER-1"),
    ("skip a STATUS", _skip_status, "R-STATE-2"),
    ("forget the duplicate memory", _forget_duplicates, "R-DUP-1"),
    ("watchdog only in motion", _watchdog_only_in_motion, "R-WD-1"),
    ("batch unasked", _batch_unasked, "R-BATCH-1"),
    ("batch without an age", _batch_without_age, "R-BATCH-2"),
    ("batch at age 0", _batch_at_age_zero, "R-BATCH-2"),
    ("drop the batch when off", _drop_batch_when_off, "R-BATCH-3"),
]


@pytest.mark.parametrize(("name", "mutate", "rule"), MUTANTS, ids=[m[0] for m in MUTANTS])
async def test_the_suite_catches_a_broken_rule(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    name: str,
    mutate: Callable[[pytest.MonkeyPatch], None],
    rule: str,
) -> None:
    mutate(monkeypatch)
    async with mirror_over("serial", tmp_path) as (_, transport):
        result = await run_suite(transport, Options(home_speed_um_s=FAST_HOME_UM_S), [rule])
    print(report(result))
    assert result.outcomes, "the rule's checks ran"
    assert rule in result.rules_failed(), f"mutant '{name}' passed the suite:\n{report(result)}"
