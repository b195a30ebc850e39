"""Running commissioning from a client of the control socket (the CLI, the demo, any tool).

`run_op` starts a run and polls `commissioning_status` until it is over, handing each progress
map to a callback; cancelling the awaiting task (Ctrl-C) sends `commissioning_cancel`, so an
interrupted run leaves the rig file untouched. `commission` runs a whole `CommissioningPlan`
(the demo's entry point): each step's result, in order, stopping at the first that fails.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from host.control.client import ControlClient

POLL_S = 0.1  # `commissioning_status` only reads the job board: a run's end is seen soon
CANCEL_TIMEOUT_S = 2.0
ProgressFn = Callable[[dict[str, Any]], None]


class RunFailedError(RuntimeError):
    """A run ended in error or was cancelled (its status says why)."""

    def __init__(self, status: dict[str, Any]) -> None:
        why = status.get("error") or status.get("reason") or status.get("state")
        super().__init__(f"{status.get('kind', 'run')} {status.get('state')}: {why}")
        self.status = status


async def run_op(
    client: ControlClient, op: str, args: dict[str, Any], on_progress: ProgressFn | None = None
) -> dict[str, Any]:
    """Start `op`, follow it, return its result (RunFailedError if it errs or is cancelled)."""
    started = await client.request(op, **args)
    job = started["job"]
    try:
        while True:
            status = await client.request("commissioning_status", job=job)
            if on_progress is not None:
                on_progress(status.get("progress", {}))
            if status.get("state") == "done":
                result: dict[str, Any] = status["result"]
                return result
            if status.get("state") != "running":
                raise RunFailedError(status)
            await asyncio.sleep(POLL_S)
    except asyncio.CancelledError:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(client.request("commissioning_cancel"), CANCEL_TIMEOUT_S)
        raise


@dataclass
class CommissioningPlan:
    """The steps to run, each an op name and its arguments (see docs/COMMISSIONING.md)."""

    steps: list[tuple[str, dict[str, Any]]] = field(default_factory=list)

    def intrinsics(
        self, board_centre_mm: list[float], stations_mm: list[float], **extra: Any
    ) -> CommissioningPlan:
        """Add an intrinsics calibration of a board around board_centre_mm."""
        self.steps.append(
            (
                "calibrate_intrinsics",
                {"board_centre_mm": board_centre_mm, "stations_mm": stations_mm, **extra},
            )
        )
        return self

    def add(self, op: str, **args: Any) -> CommissioningPlan:
        """Add any commissioning op with its arguments (calibrate_head, calibrate_check, …)."""
        self.steps.append((op, args))
        return self


async def commission(
    client: ControlClient, plan: CommissioningPlan, on_progress: ProgressFn | None = None
) -> list[tuple[str, dict[str, Any]]]:
    """Run the plan's steps in order; stop after the first that does not pass."""
    results: list[tuple[str, dict[str, Any]]] = []
    for op, args in plan.steps:
        result = await run_op(client, op, args, on_progress)
        results.append((op, result))
        if not result.get("passed", False):
            break
    return results
