"""The daemon on the emulated rig, seen from outside as a render engine and a supervisor see it:
poses on the bus and as OpenTrackIO samples are the registered ones, the rig answers a status
query on the bus, and its liveliness token goes when the daemon stops."""

from __future__ import annotations

import asyncio
import json
import signal
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from host.bus.fleet import Fleet
from host.bus.messages import key, unpack
from host.bus.session import zenoh_config
from host.outputs.opentrackio_packet import Reassembler, decode_segment
from tests.bus.test_bus import wait_until
from tests.hil_rig import Rigs, free_port
from tests.outputs.test_opentrackio import VALIDATOR, rot
from tests.service.test_daemon import connect

EXTRA = """
[bus]
enabled = true
rig_id = "hall-rig-7"
listen = ["tcp/127.0.0.1:{bus_port}"]
stats_interval_s = 0.2
[outputs.opentrackio]
enabled = true
destinations = ["127.0.0.1:{otio_port}"]
"""


class Datagrams(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.got: asyncio.Queue[bytes] = asyncio.Queue()

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.got.put_nowait(data)


async def next_sample(receiver: Datagrams) -> dict[str, Any]:
    """The next whole OpenTrackIO sample."""
    joiner = Reassembler()
    while True:
        payload = joiner.feed(decode_segment(await asyncio.wait_for(receiver.got.get(), 10)))
        if payload is not None:
            sample: dict[str, Any] = json.loads(payload)
            return sample


async def test_daemon_on_the_bus_and_as_opentrackio(hil_rig: Rigs) -> None:
    loop = asyncio.get_running_loop()
    udp, receiver = await loop.create_datagram_endpoint(Datagrams, local_addr=("127.0.0.1", 0))
    bus_port, otio_port = free_port(), udp.get_extra_info("sockname")[1]
    rig = hil_rig(sections=EXTRA.format(bus_port=bus_port, otio_port=otio_port))
    await asyncio.to_thread(rig.start_sim)
    notes = await rig.start_daemon_notified()
    daemon = rig.daemon
    assert daemon is not None
    peer = zenoh.open(zenoh_config("peer", [], [f"tcp/127.0.0.1:{bus_port}"], False))
    fleet = Fleet(peer)
    try:
        await notes.wait_for("READY=1", 20.0)
        fleet.start()
        await wait_until(lambda: [r["rig"] for r in fleet.rows() if r["alive"]] == ["hall-rig-7"])
        bus_poses: list[dict[str, Any]] = []
        sub = peer.declare_subscriber(
            key("hall-rig-7", "pose"), lambda s: bus_poses.append(unpack(s.payload.to_bytes()))
        )
        async with await connect(Path(rig.socket_path)) as client:
            await client.request("subscribe", topics=["pose"])
            event = (await client.next_event(timeout_s=10))["data"]
            await wait_until(
                lambda: any(p["frame_index"] == event["frame_index"] for p in bus_poses)
            )
            on_bus = next(p for p in bus_poses if p["frame_index"] == event["frame_index"])
            assert on_bus["T_w_c"] == event["T_w_c"]
            assert on_bus["t_ns"] == event["t_ns"]
            assert on_bus["head_rad"] == event["head_rad"]  # pan, tilt at the exposure
            assert len(event["head_rad"]) == 2
            assert all(abs(a) < 3.2 for a in event["head_rad"])
        sub.undeclare()
        await wait_until(lambda: fleet.rows()[0]["link_up"] is True)
        replies = await loop.run_in_executor(
            None, lambda: list(peer.get(key("hall-rig-7", "status"), timeout=5.0))
        )
        answer = replies[0].ok
        assert answer is not None
        status = unpack(answer.payload.to_bytes())["status"]
        assert status["link_up"] is True
        assert status["service"]["bus"]["rig"] == "hall-rig-7"
        assert status["service"]["opentrackio"]["sent"] > 0
        sample = await next_sample(receiver)
        assert not list(VALIDATOR.iter_errors(sample))
        got = sample["transforms"][0]
        R = rot("z", got["rotation"]["pan"]) @ rot("x", got["rotation"]["tilt"])
        R = R @ rot("y", got["rotation"]["roll"])
        T = np.array(event["T_w_c"])
        np.testing.assert_allclose(R, np.column_stack([T[:3, 0], T[:3, 2], -T[:3, 1]]), atol=1e-3)
        assert abs(got["translation"]["z"] - 4.0) < 0.2  # the runway is 4 m up
        daemon.send_signal(signal.SIGTERM)
        assert await rig.daemon_exit(3.0) == 0
        await wait_until(lambda: fleet.rows()[0]["alive"] is False)
    finally:  # the processes end with hil_rig
        fleet.close()
        peer.close()
        await notes.close()
        udp.close()
