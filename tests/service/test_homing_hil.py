"""HIL: every pose the daemon publishes while homing lies among the encoder samples around it.

Homing latches the encoder's index: the count jumps by wherever the controller's power-up zero
was. A pose made from samples on both sides of that jump is a position the trolley never had
(one recorded session published s = 774.6 mm between samples at −337 mm and +148 mm). The daemon
records its encoder samples; each published pose is checked against the recorded samples of its
own segment around its time, the homing latch included.
"""

from __future__ import annotations

import asyncio
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from host.control.client import ControlClient
from host.recording import RecordingReader
from host.recording.writer import KIND_ENCODER
from host.service.wiring import ENCODER_HORIZON_NS
from protocol.enums import Inputs
from tests.hil_rig import HOME_S_MM, Rigs
from tests.recording.test_recording_hil import HOME_SPEED_UM_S, recording_rig
from tests.service.test_daemon import connect

# A pose at 200 Hz (one per encoder sample) meets the instant after the latch on every run.
POSE_RATE_HZ = 200.0
# The publisher carries the newest sample forward along its velocity for up to the horizon: a
# pose lies among the samples of one segment within that of its time, or beyond them by at most
# that carry (a late sample under load, a reversal), give or take a mark's correction.
WINDOW_NS = ENCODER_HORIZON_NS + 30_000_000
TOLERANCE_MM = 3.0


@dataclass(frozen=True)
class Recorded:
    """The recorded encoder samples: host times, track s (controller mm + home), speed, segment."""

    t_ns: np.ndarray
    s_mm: np.ndarray
    speed_mm_s: np.ndarray
    segment: np.ndarray  # numbered runs of samples with the same HOMED flag

    @classmethod
    def read(cls, rec: Path) -> Recorded:
        """From a recording directory."""
        rows = [
            (r.t_ns, HOME_S_MM + r.data["s_mm"], abs(r.data["v_mm_s"]), r.data["inputs"])
            for r in RecordingReader([rec])
            if r.kind == KIND_ENCODER
        ]
        t, s, v, inputs = (np.array(column) for column in zip(*rows, strict=True))
        homed = (inputs & int(Inputs.HOMED)) != 0
        return cls(t, s, v, np.concatenate([[0], np.cumsum(homed[1:] != homed[:-1])]))

    def among(self, pose: dict[str, Any]) -> bool:
        """Whether the pose lies among the samples of one segment near its time."""
        near = np.abs(self.t_ns - pose["t_ns"]) <= WINDOW_NS
        assert near.any()  # the recording spans every published pose
        for k in np.unique(self.segment[near]):
            mine = near & (self.segment == k)
            s = self.s_mm[mine]
            slack = TOLERANCE_MM + self.speed_mm_s[mine].max() * ENCODER_HORIZON_NS / 1e9
            if s.min() - slack <= pose["s_mm"] <= s.max() + slack:
                return True
        return False


async def poses_while_homing_and_moving(client: ControlClient) -> list[dict[str, Any]]:
    """Subscribe before HOME, then home and move 300 mm; every pose published on the way."""
    deadline = time.monotonic() + 20.0
    while not (await client.request("status"))["link_up"]:
        assert time.monotonic() < deadline, "the controller link did not come up"
        await asyncio.sleep(0.1)
    await client.request("param_set", param="HOME_SPEED_UM_S", value=HOME_SPEED_UM_S)
    await client.request("subscribe", topics=["pose"])
    await client.request("home")
    poses: list[dict[str, Any]] = []
    moved = seen_moving = False
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        event = await client.next_event(timeout_s=5)
        if event["topic"] != "pose":
            continue
        pose = event["data"]
        poses.append(pose)
        seen_moving |= moved and pose["state"] == "MOVING"
        if not moved and pose["homed"] and pose["state"] == "READY":
            await client.request("move", position_mm=300.0, speed_mm_s=400.0)
            moved = True
        elif seen_moving and pose["state"] == "READY":
            return poses
    raise AssertionError(f"homing and the move did not end; last pose {poses[-1:]}")


async def test_no_pose_bridges_the_homing_latch(hil_rig: Rigs) -> None:
    rig = await asyncio.to_thread(recording_rig, hil_rig, POSE_RATE_HZ)
    daemon = rig.start_daemon()
    async with await connect(Path(rig.socket_path)) as client:
        poses = await poses_while_homing_and_moving(client)
    daemon.send_signal(signal.SIGTERM)
    assert await rig.daemon_exit(5.0) == 0
    recorded = Recorded.read(rig.dir / "rec")
    steps = np.diff(recorded.segment)
    assert steps.sum() == 1  # the emulator starts unhomed: the latch is the one change
    latch = int(np.flatnonzero(steps)[0]) + 1
    jump_mm = abs(recorded.s_mm[latch] - recorded.s_mm[latch - 1])
    assert sum(not p["homed"] for p in poses) > 5  # published while seeking, before the latch
    assert sum(p["homed"] for p in poses) > 5
    off = [(p["t_ns"], round(p["s_mm"], 3)) for p in poses if not recorded.among(p)]
    assert not off, f"poses off the samples around them (the latch jumped {jump_mm:.1f} mm): {off}"
