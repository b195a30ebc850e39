"""The demo runs the daemon's own code on the simulated rig, reachable over a control socket."""

from __future__ import annotations

import asyncio
from pathlib import Path

from hil_sim.rig_scenario import scenario_for_rig
from host.control.client import ControlClient
from host.demo.daemon_phase import running_daemon
from host.demo.rigs import paper_demo_rig
from host.demo.world import SimWorld
from host.rig import save_rig

START_TIMEOUT_S = 15.0


async def _link_up(client: ControlClient) -> dict[str, object]:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + START_TIMEOUT_S
    status: dict[str, object] = {}
    while loop.time() < deadline:
        status = await client.request("status")
        if status.get("link_up"):
            return status
        await asyncio.sleep(0.1)
    raise AssertionError(f"link never came up: {status}")


async def test_daemon_serves_the_simulated_rig_over_its_control_socket(tmp_path: Path) -> None:
    spec = paper_demo_rig()
    rig = tmp_path / "rig.toml"
    save_rig(spec, rig)
    world = SimWorld(scenario_for_rig(spec, seed=1), "pty")
    await world.start()
    try:
        async with running_daemon(world, rig, tmp_path / "daemon") as running:
            client = await ControlClient.connect_unix(str(running.socket_path))
            async with client:
                await _link_up(client)
                calibration = await client.request("calibration")
                assert calibration["source"] == str(rig)
                assert calibration["m_cr"][0][3] == spec.head.m_cr.matrix[0, 3]
            assert await running.reload() == []  # the rig file has not changed
        assert not running.socket_path.exists()  # stopped and cleaned up
    finally:
        await world.stop()
