"""`orbitar daemon` on the real link: emulator and daemon as processes, a fake notify socket.

The emulator (`python -m hil_sim --link pty`) serves the firmware mirror on a pty; the daemon
reaches it through the configured serial link with no camera, so poses come from the encoder at a
fixed rate. The operator's CLI (`orbitar status/home/move`) drives the simulated trolley.
"""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from host.config import Config
from host.control.client import ControlClient
from tests.hil_rig import HOME_S_MM, HilRig, Notifications, Rigs, daemon_config, rig_toml
from tests.service.test_daemon import connect

WATCHDOG_USEC = "400000"
HOME_SPEED_UM_S = 150_000  # the default 50 mm/s would spend ~8 s of the test homing
POSITION_TOLERANCE_MM = 3.0


async def cli(rig: HilRig, *args: str) -> tuple[int, str]:
    """`orbitar ARGS --socket …` as an operator types it, off the event loop."""
    return await asyncio.to_thread(rig.cli, *args, timeout_s=20.0)


async def status(rig: HilRig) -> dict[str, Any]:
    """`orbitar status --json`, parsed."""
    code, out = await cli(rig, "status", "--json")
    assert code == 0, out
    result: dict[str, Any] = json.loads(out)
    return result


async def wait_until_at(
    client: ControlClient, target_mm: float, timeout_s: float, tol_mm: float = POSITION_TOLERANCE_MM
) -> None:
    """Poll the controller snapshot until it rests in READY within tol_mm of the target."""
    deadline = time.monotonic() + timeout_s
    last: dict[str, Any] = {}
    while time.monotonic() < deadline:
        last = (await client.request("status"))["controller"]
        position = last.get("position_mm")
        at = position is not None and abs(position - target_mm) < tol_mm
        if last.get("state") == "READY" and at:
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"not at {target_mm} mm: {last}")


@pytest.fixture
async def notified_rig(hil_rig: Rigs) -> AsyncIterator[tuple[HilRig, Notifications]]:
    """Emulator, then daemon (its processes end with hil_rig)."""
    rig = hil_rig()
    await asyncio.to_thread(rig.start_sim)
    notes = await rig.start_daemon_notified(WATCHDOG_USEC=WATCHDOG_USEC)
    try:
        yield rig, notes
    finally:
        await notes.close()


async def test_daemon_drives_the_emulated_trolley(
    notified_rig: tuple[HilRig, Notifications],
) -> None:
    rig, notes = notified_rig
    ready = await notes.wait_for("READY=1", 20.0)
    assert "controller link up" in ready
    assert await notes.wait_for("WATCHDOG=1", 2.0)
    first = await status(rig)
    for _ in range(50):  # the link is up at the handshake; the first STATUS follows it
        if first["controller"]["state"] != "UNKNOWN":
            break
        await asyncio.sleep(0.1)
        first = await status(rig)
    assert first["link_up"] is True
    assert first["controller"]["link"] == "up"
    assert first["controller"]["state"] in ("IDLE", "READY")
    async with await connect(Path(rig.socket_path)) as client:
        await client.request("param_set", param="HOME_SPEED_UM_S", value=HOME_SPEED_UM_S)
        code, out = await cli(rig, "home")
        assert code == 0, out
        # Homing ends on the index pulse; a fast seek may lose a few steps on the way back.
        await wait_until_at(client, 0.0, 15.0, tol_mm=10.0)
        code, out = await cli(rig, "move", "300", "--speed", "400")
        assert code == 0, out
        await wait_until_at(client, 300.0, 10.0)
        await client.request("subscribe", topics=["pose"])
        pose = (await client.next_event(timeout_s=5))["data"]
        stats = await client.request("link_stats")
        # The pose is on the corrected track position; the raw one adds the configured home.
        assert pose["s_mm"] == pytest.approx(stats["track_s_mm"], abs=0.01)
        assert stats["raw_s_mm"] == pytest.approx(HOME_S_MM + 300.0, abs=POSITION_TOLERANCE_MM)
        assert pose["state"] == "READY"
        assert abs(pose["T_w_c"][2][3] - 4000.0) < 200.0  # the runway is 4 m up
        assert stats["handshakes"] == 1
        assert stats["frames_in"] > 100
        assert stats["homed"] is True
        assert stats["marks_seen"] >= 1  # REF_MARK over the wire into the feed
        assert "chain_scale" in stats
    shown = await status(rig)
    assert abs(shown["controller"]["position_mm"] - 300.0) < POSITION_TOLERANCE_MM
    assert shown["service"]["fps"] > 10.0  # poses published without a camera
    pings = sum(text == "WATCHDOG=1" for text in notes.got)
    assert pings >= 10  # every 0.2 s (half of WATCHDOG_USEC) for the whole run
    assert rig.daemon is not None
    rig.daemon.send_signal(signal.SIGTERM)
    assert await rig.daemon_exit(2.0) == 0
    await notes.wait_for("STOPPING=1", 1.0)
    log = rig.log_tail(10**9)
    assert "controlled stop acknowledged" in log
    assert not (rig.dir / "ctl.sock").exists()


async def test_daemon_waits_for_a_missing_controller_then_connects(hil_rig: Rigs) -> None:
    rig = hil_rig()
    notes = await rig.start_daemon_notified(WATCHDOG_USEC=WATCHDOG_USEC)  # no emulator, no pty yet
    try:
        client = await connect(Path(rig.socket_path))
        async with client:
            early = await client.request("status")
            assert early["link_up"] is False
            assert early["service"]["link_error"]
            await asyncio.to_thread(rig.start_sim)
            ready = await notes.wait_for("READY=1", 20.0)
            assert "controller link up" in ready
            assert (await client.request("status"))["link_up"] is True
        assert rig.daemon is not None
        rig.daemon.send_signal(signal.SIGTERM)
        assert await rig.daemon_exit(2.0) == 0
    finally:
        await notes.close()


async def test_a_controller_built_for_another_chain_is_named_in_status(hil_rig: Rigs) -> None:
    """The rig file's chain is ISO 10B on a 17-tooth sprocket; the emulated controller is the
    reference build (08B, 20 teeth): the daemon keeps running on the controller's pitch and
    says what differs, in the status op and in `orbitar status`."""
    rig = hil_rig(rig=rig_toml() + "[track.chain]\nsprocket_teeth = 17\npitch_mm = 15.875\n")
    await asyncio.to_thread(rig.start_sim)
    notes = await rig.start_daemon_notified(WATCHDOG_USEC=WATCHDOG_USEC)
    try:
        assert "controller link up" in await notes.wait_for("READY=1", 20.0)
        problem = (await status(rig))["service"]["drive_problem"]
        assert problem == (
            "sprocket 20 teeth, the rig file's 17; pitch 12.7 mm, the rig file's 15.875 mm"
        )
        code, text = await cli(rig, "status")
        assert code == 0, text
        assert f"controller built for another chain: {problem}" in text
    finally:
        await notes.close()


async def test_bad_model_path_is_a_clear_exit_2(tmp_path: Path) -> None:
    config = tmp_path / "orbitar.toml"
    text = daemon_config(tmp_path).replace('source = "none"', f'source = "{tmp_path}/x.avi"')
    config.write_text(text)
    (tmp_path / "rig.toml").write_text(
        rig_toml() + f'[workpiece]\nmodel = "{tmp_path}/missing.obj"\n'
    )
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "host.service", "daemon", "--config", str(config),
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    _, err = await asyncio.wait_for(proc.communicate(), 20.0)
    assert proc.returncode == 2
    assert "missing.obj" in err.decode()


# ---- the wiring's pieces, in process -------------------------------------------------------


def test_custom_track_rig_builds_the_same_runway() -> None:
    from host.service.wiring import build_rig, build_track
    from tests.rig.helpers import rig_config

    segments = "".join(
        f'[[track.segments]]\nkind = "straight"\nlength_mm = {length}\n'
        '[[track.segments]]\nkind = "arc"\nradius_mm = 1000.0\nangle_deg = 90.0\n'
        for length in (4000.0, 1000.0, 4000.0, 1000.0)
    )
    placement = "[track.placement]\nmatrix = [[1,0,0,0],[0,1,0,0],[0,0,1,4000],[0,0,0,1]]\n"
    custom = rig_config(segments + placement)
    track, preset = build_track(custom), build_track(Config())
    assert abs(track.length_mm - preset.length_mm) < 1e-9
    assert track.closed
    # Same shape; the custom track starts at the world origin, the preset at the runway corner.
    offset = preset.pose(0.0)[:3, 3] - track.pose(0.0)[:3, 3]
    for s_mm in (0.0, 2500.0, 7000.0, 13000.0):
        assert abs(track.pose(s_mm)[:3, 3] + offset - preset.pose(s_mm)[:3, 3]).max() < 1e-6
    rig = build_rig(custom)
    assert abs(rig.T_r_c[:3, 3] - [50.843, 47.094, 76.177]).max() < 1e-9


def test_pose_publisher_publishes_only_from_samples() -> None:
    from host.config import Config
    from host.control.api import PoseSample
    from host.service.wiring import STREAM_RATES_HZ, PosePublisher, build_pose_source

    poses, feed = build_pose_source(Config(), STREAM_RATES_HZ["serial"])
    feed.home_s_mm = 100.0
    got: list[PoseSample] = []

    class _Ctl:
        def snapshot(self) -> dict[str, Any]:
            return {"state": "MOVING"}

    publisher = PosePublisher(poses, _Ctl(), got.append, 30.0)  # type: ignore[arg-type]
    assert not publisher.publish(1_000_000_000)
    assert publisher.stale == 1
    for i in range(5):
        t_ns = 1_000_000_000 + i * 5_000_000
        feed.on_encoder(t_ns, 10.0 * i, 2000.0, 0)
        feed.on_head(t_ns, 0.0, 0.0)
    assert publisher.publish(1_000_000_000 + 25_000_000)  # 5 ms past the newest: extrapolated
    assert got[-1].state == "MOVING"
    assert abs((got[-1].s_mm or 0.0) - 150.0) < 1e-6  # 100 mm home offset + 50 mm along
    assert not publisher.publish(1_000_000_000 + 500_000_000)  # far past: stale, never a guess
    assert publisher.published == 1


def test_without_a_camera_poses_follow_a_radios_lag_instead_of_going_stale() -> None:
    # XBee-like: encoder batches of 5 samples (10 ms apart) leave every 50 ms and arrive 20 ms
    # after their newest sample. A pose for "now" is then carried up to 70 ms past the newest
    # sample, beyond the 50 ms horizon; the publisher makes each for now less the recent lag.
    from host.config import Config
    from host.control.api import PoseSample
    from host.service.wiring import STREAM_RATES_HZ, PosePublisher, build_pose_source

    def run(follow_lag: bool) -> tuple[int, int, list[PoseSample]]:
        poses, feed = build_pose_source(Config(), STREAM_RATES_HZ["xbee"])
        got: list[PoseSample] = []

        class _Ctl:
            def snapshot(self) -> dict[str, Any]:
                return {"state": "MOVING", "homed": True}

        publisher = PosePublisher(poses, _Ctl(), got.append, 30.0, feed)  # type: ignore[arg-type]
        ms, t0 = 1_000_000, 1_000_000_000
        stamps = [t0 + 10 * ms * k for k in range(300)]
        arrivals = [t0 + 50 * ms * (k // 5) + 60 * ms for k in range(300)]
        pushed = 0
        for tick in range(t0 + 200 * ms, t0 + 2_900 * ms, 33 * ms):
            while pushed < len(stamps) and arrivals[pushed] <= tick:
                feed.on_encoder(stamps[pushed], 0.5 * (stamps[pushed] - t0) / ms, 500.0, 1)
                feed.on_head(stamps[pushed], 0.0, 0.0)
                pushed += 1
            publisher.publish(publisher.pose_time(tick) if follow_lag else tick)
        return publisher.published, publisher.stale, got

    _, stale_now, _ = run(follow_lag=False)
    published, stale, got = run(follow_lag=True)
    assert stale_now > 20  # for "now" a third of the ticks or more had no pose
    assert stale == 0
    for pose in got:  # made from samples around the instant it is stamped with: exact
        assert pose.s_mm == pytest.approx(0.5 * (pose.t_ns - 1_000_000_000) / 1_000_000, abs=1e-6)
    assert published == len(got) > 70
