"""The bus on loopback (multicast scouting off): poses, state on change, statistics, queries,
liveliness, `orbitar fleet`, and a bus that cannot open without harm to the daemon."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import time
from collections.abc import AsyncIterator, Callable, Mapping
from typing import Any

import numpy as np
import pytest
import zenoh

from host.bus.fleet import Fleet, format_table, run_fleet
from host.bus.messages import key, unpack
from host.bus.publisher import BusPublisher
from host.bus.session import zenoh_config
from host.cli import build_parser
from host.config_bus import BusConfig
from host.control.api import PoseSample
from tests.hil_rig import free_port

WAIT_S = 5.0


async def wait_until(check: Callable[[], bool], timeout_s: float = WAIT_S) -> None:
    """Poll a condition set from Zenoh's threads."""
    deadline = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > deadline:
            raise TimeoutError
        await asyncio.sleep(0.02)


class Rig:
    """A publisher with fake providers, listening on its own loopback port."""

    def __init__(self, name: str, port: int) -> None:
        self.status_calls = 0
        self.fail_status = False
        self.stats = {"link_up": True, "fps": 30.0}
        config = BusConfig(enabled=True, rig_id=name, listen=(f"tcp/127.0.0.1:{port}",))
        self.bus = BusPublisher(
            config, status=self._status, rig=self._rig, stats=lambda: self.stats
        )

    async def _status(self) -> Mapping[str, Any]:
        self.status_calls += 1
        if self.fail_status:
            raise RuntimeError("no status today")
        return {"link_up": True, "controller": {"state": "READY"}}

    async def _rig(self) -> Mapping[str, Any]:
        return {"intrinsics": {"fx": 3676.462}}


@pytest.fixture
async def rig() -> AsyncIterator[tuple[Rig, zenoh.Session, int]]:
    port = free_port()
    r = Rig("rig-a", port)
    task = asyncio.create_task(r.bus.run())
    await wait_until(lambda: r.bus.up)
    peer = zenoh.open(zenoh_config("peer", [], [f"tcp/127.0.0.1:{port}"], False))
    try:
        yield r, peer, port
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        await r.bus.close()
        peer.close()


def collect(session: zenoh.Session, selector: str) -> tuple[list[dict[str, Any]], Any]:
    """Decoded payloads arriving on a selector."""
    got: list[dict[str, Any]] = []
    sub = session.declare_subscriber(selector, lambda s: got.append(unpack(s.payload.to_bytes())))
    return got, sub


async def test_poses_state_and_stats_reach_a_subscriber(
    rig: tuple[Rig, zenoh.Session, int],
) -> None:
    r, peer, _ = rig
    poses, s1 = collect(peer, key("*", "pose"))
    states, s2 = collect(peer, key("rig-a", "state"))
    stats, s3 = collect(peer, key("rig-a", "stats"))
    await asyncio.sleep(0.5)  # the subscriptions reach the publisher's side
    T = np.eye(4)
    T[:3, 3] = (1500.0, 0.0, 4000.0)
    t_ns = time.monotonic_ns()
    r.bus.publish_pose(PoseSample(t_ns, T, "MOVING", 1500.0, 42))
    for state in ("READY", "READY", "MOVING"):
        r.bus.publish_state({"state": state, "position_mm": 1500.0})
    await wait_until(lambda: bool(poses) and len(states) >= 2 and bool(stats))
    pose = poses[0]
    assert (pose["v"], pose["rig"], pose["frame_index"], pose["t_ns"]) == (1, "rig-a", 42, t_ns)
    assert pose["T_w_c"][0][3] == 1500.0
    assert abs(pose["t_unix_ns"] - time.time_ns()) < 2e9
    assert [s["state"] for s in states] == ["READY", "MOVING"]  # published on change only
    assert stats[0]["link_up"] is True
    for sub in (s1, s2, s3):
        sub.undeclare()


async def test_status_and_rig_queries_answer_from_the_daemon(
    rig: tuple[Rig, zenoh.Session, int],
) -> None:
    r, peer, _ = rig
    loop = asyncio.get_running_loop()

    def ask(name: str) -> list[Any]:
        return list(peer.get(key("*", name), timeout=WAIT_S))

    replies = await loop.run_in_executor(None, ask, "status")
    assert len(replies) == 1
    assert replies[0].ok is not None
    body = unpack(replies[0].ok.payload.to_bytes())
    assert body["status"]["controller"]["state"] == "READY"
    assert str(replies[0].ok.key_expr) == "orbitar/rig-a/status"
    rig_replies = await loop.run_in_executor(None, ask, "rig")
    assert unpack(rig_replies[0].ok.payload.to_bytes())["rig"]["intrinsics"]["fx"] == 3676.462
    r.fail_status = True
    failed = await loop.run_in_executor(None, ask, "status")
    assert failed[0].err is not None
    assert "no status today" in unpack(failed[0].err.payload.to_bytes())["error"]
    assert r.status_calls == 2


async def test_fleet_sees_rigs_come_and_go(rig: tuple[Rig, zenoh.Session, int]) -> None:
    r, peer, _ = rig
    fleet = Fleet(peer)
    fleet.start()
    try:
        await wait_until(lambda: [row["alive"] for row in fleet.rows()] == [True])
        r.bus.publish_state({"state": "HOMING", "position_mm": -3.25})
        await wait_until(lambda: fleet.rows()[0]["state"] == "HOMING")
        assert "rig-a" in format_table(fleet.rows())
        assert "-3.2 mm" in format_table(fleet.rows())
        await r.bus.close()
        await wait_until(lambda: fleet.rows()[0]["alive"] is False)
        assert "gone" in format_table(fleet.rows())
    finally:
        fleet.close()


async def test_a_fleet_that_joins_late_sees_the_last_state(
    rig: tuple[Rig, zenoh.Session, int],
) -> None:
    r, peer, _ = rig
    r.bus.publish_state({"state": "FAULT", "position_mm": 812.0})  # before anyone listens
    fleet = Fleet(peer)
    fleet.start()
    try:
        await wait_until(lambda: [row["state"] for row in fleet.rows()] == ["FAULT"])
        assert fleet.rows()[0]["position_mm"] == 812.0
    finally:
        fleet.close()


async def test_orbitar_fleet_once_prints_json(rig: tuple[Rig, zenoh.Session, int]) -> None:
    r, _, port = rig
    r.bus.publish_state({"state": "READY", "position_mm": 10.0})
    args = build_parser("fleet").parse_args(
        ["fleet", "--once", "--json", "--wait", "1.0", "--connect", f"tcp/127.0.0.1:{port}"]
    )
    out = io.StringIO()
    code = await asyncio.get_running_loop().run_in_executor(None, run_fleet, args, out)
    assert code == 0
    rows = json.loads(out.getvalue())["rigs"]
    assert [(row["rig"], row["alive"]) for row in rows] == [("rig-a", True)]


async def test_a_bus_that_cannot_open_is_retried_and_reported() -> None:
    config = BusConfig(enabled=True, rig_id="lonely", mode="client", connect=("tcp/127.0.0.1:1",))

    async def nothing() -> Mapping[str, Any]:
        return {}

    bus = BusPublisher(config, status=nothing, rig=nothing, stats=dict)
    task = asyncio.create_task(bus.run())
    await wait_until(lambda: "Unable to connect" in bus.error)
    bus.publish_pose(PoseSample(0, np.eye(4), "READY"))  # dropped quietly while down
    assert bus.stats()["up"] is False
    assert bus.stats()["pose"] == 0
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
    await bus.close()


def test_rig_name_defaults_to_a_valid_host_name() -> None:
    from host.config_bus import rig_name

    name = rig_name(BusConfig())
    assert name
    assert "/" not in name
    assert "*" not in name
    assert rig_name(BusConfig(rig_id="hall-3.rig-2")) == "hall-3.rig-2"
