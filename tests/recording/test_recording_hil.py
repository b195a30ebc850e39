"""HIL: the daemon records a session with the emulator; the replay from raw bytes gives its poses.

The trolley is homed and moved while the daemon records; then `orbitar replay` re-runs the link
(framing, clock sync, drift filter) from the recorded bytes with the configuration from the
recording's header, and every pose the daemon published (as a subscriber received it) comes back
within POSE_TOLERANCE_MM. A reload then points the recording at a directory that cannot be made
(its parent is a plain file): the daemon runs on, says so in `status`, and records by itself once
the directory can be made; that file, begun mid-session, replays from its header's identity.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from host.control.client import ControlClient
from host.recording import RecordingReader
from host.service.replay_registration import run as replay_run
from tests.hil_rig import HilRig, Rigs
from tests.service.test_daemon import connect
from tests.service.test_daemon_hil import wait_until_at

RECORDING = """
[recording]
enabled = true
dir = "{dir}/{rec}"
"""
HOME_SPEED_UM_S = 150_000
FPS = 20.0  # poses published per second without a camera
# The session stamps its clock probes with the transport's stamps, which the tap records: the
# replayed clock is the live one exactly, and the poses agree to the replay's printed rounding.
POSE_TOLERANCE_MM = 1e-5
CLOCK_TOLERANCE_US = 0.0


async def recording_status(client: ControlClient) -> dict[str, Any]:
    """The recording part of `status`."""
    shown: dict[str, Any] = (await client.request("status"))["service"]["recording"]
    return shown


async def wait_recording_state(client: ControlClient, state: str) -> dict[str, Any]:
    """Poll `status` until the recording is in `state` (after an error, for a failing state)."""
    deadline = time.monotonic() + 15.0
    while True:
        shown = await recording_status(client)
        if shown["state"] == state and (state == "recording" or shown["errors"]):
            return shown
        assert time.monotonic() < deadline, shown
        await asyncio.sleep(0.1)


def recording_rig(rigs: Rigs, fps: float = FPS) -> HilRig:
    """A rig whose daemon records into dir/rec and publishes `fps` poses a second (the rig
    file's rate); its emulator started, its daemon not yet."""
    rig = rigs(fps=fps)
    rig.write_config(sections=RECORDING.format(dir=rig.dir, rec="rec"))
    rig.start_sim()
    return rig


async def drive_and_listen(client: ControlClient) -> list[dict[str, Any]]:
    """Home, then move, collecting the poses published until the trolley rests again."""
    await client.request("param_set", param="HOME_SPEED_UM_S", value=HOME_SPEED_UM_S)
    await client.request("home")
    await wait_until_at(client, 0.0, 20.0, tol_mm=10.0)
    await client.request("subscribe", topics=["pose"])
    await client.request("move", position_mm=300.0, speed_mm_s=400.0)
    poses: list[dict[str, Any]] = []
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:  # until the move is over: READY after MOVING
        event = await client.next_event(timeout_s=5)
        if event["topic"] == "pose":
            poses.append(event["data"])
            moved = any(p["state"] == "MOVING" for p in poses)
            if moved and poses[-1]["state"] == "READY":
                return poses
    raise AssertionError(f"the move did not end; last pose {poses[-1:]}")


def replay(rec: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> dict[str, str]:
    """`orbitar replay REC --source raw --out OUT`; its summary line."""
    args = argparse.Namespace(files=[str(rec)], config=None, source="raw", out=str(out))
    capsys.readouterr()
    assert replay_run(args) == 0
    err = capsys.readouterr().err
    assert "as recorded in" in err  # the configuration came from the header
    return dict(item.split("=", 1) for item in err.strip().splitlines()[-1].split())


async def test_replay_from_raw_bytes_gives_the_live_poses(
    hil_rig: Rigs, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = await asyncio.to_thread(recording_rig, hil_rig)
    daemon = rig.start_daemon()
    await asyncio.to_thread(rig.wait_link_up)
    async with await connect(Path(rig.socket_path)) as client:
        shown = await wait_recording_state(client, "recording")
        assert Path(shown["file"]).exists()
        live = await drive_and_listen(client)
        shown = await recording_status(client)
        assert shown["bytes"] > 10_000
        assert shown["dropped"] == 0
        (rig.dir / "disk").write_text("a plain file where a directory should be")
        rig.write_config(sections=RECORDING.format(dir=rig.dir, rec="disk/rec"))
        daemon.send_signal(signal.SIGHUP)
        blocked = await wait_recording_state(client, "retrying")
        assert "ENOTDIR" in blocked["last_error"] or "EEXIST" in blocked["last_error"]
        assert blocked["file"] is None  # no file named that does not exist
        (rig.dir / "disk").unlink()  # the disk is usable again: no restart needed
        shown = await wait_recording_state(client, "recording")
        assert Path(shown["file"]).exists()
        await client.request("move", position_mm=100.0, speed_mm_s=400.0)
        await wait_until_at(client, 100.0, 10.0)
    daemon.send_signal(signal.SIGTERM)
    assert await rig.daemon_exit(5.0) == 0
    header = next(iter(RecordingReader([rig.dir / "rec"], strict=True))).data
    assert header["version"] == 2
    assert "[recording]" in header["config_toml"]
    assert header["calibration"]["intrinsics"]["fx"] > 0
    out = tmp_path / "replayed.jsonl"
    summary = replay(rig.dir / "rec", out, capsys)
    assert summary["source"] == "raw"
    assert int(summary["raw_samples"]) > 500
    assert float(summary["clock_delta_max_us"]) <= CLOCK_TOLERANCE_US
    with capsys.disabled():  # shown with pytest -s
        print("\nreplay summary:", " ".join(f"{k}={v}" for k, v in summary.items()))
    replayed = {p["t_ns"]: p for p in map(json.loads, out.read_text().splitlines())}
    moving = [p for p in live if 10.0 < p["s_mm"] - 150.0 < 290.0]
    assert len(moving) > 5  # poses taken while the trolley moved, not only at rest
    for pose in live:
        again = replayed[pose["t_ns"]]
        assert again["status"] == "ok"
        delta = np.asarray(again["T_w_c"])[:3, 3] - np.asarray(pose["T_w_c"])[:3, 3]
        assert np.linalg.norm(delta) < POSE_TOLERANCE_MM
        assert again["s_mm"] == pytest.approx(pose["s_mm"], abs=POSE_TOLERANCE_MM)
    # The file begun after the reload has no IDENTIFY: the header's identity converts it.
    late = replay(rig.dir / "disk" / "rec", tmp_path / "late.jsonl", capsys)
    assert int(late["raw_samples"]) > 100
