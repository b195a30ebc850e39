"""The firmware mirror in a real-time runner behind an emulated link, for the suite to check."""

from __future__ import annotations

import asyncio
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from hil_sim.links.can_node import VirtualCanNode
from hil_sim.links.endpoint import SimPortEndpoint
from hil_sim.links.pacing import uart_rate_bytes_s
from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.xbee import CONTROLLER_ADDR64, XBeeModule
from hil_sim.runner import RealtimeRunner, Simulation
from hil_sim.scenario import Scenario
from host.transport import Transport, create_transport

UART_BAUD = 115200
# What the controller's link takes: the UART's line rate, or for an XBee what the module hands
# on (it holds CTS off when its buffer fills): 4.4 kB/s of air shared by both directions, 18 B
# of overhead per packet, and the host's heartbeats take their share.
XBEE_THROUGHPUT_BYTES_S = 1_000.0
FAST_HOME_UM_S = 200_000  # the mirror's rig homes in about a second at this speed


@asynccontextmanager
async def mirror_over(kind: str, tmp: Path) -> AsyncIterator[tuple[RealtimeRunner, Transport]]:
    """The mirror behind a pty UART ("serial"), an XBee pair ("xbee") or a CAN node ("can")."""
    runner = RealtimeRunner(Simulation(Scenario(seed=11)))
    # The board's link carries no more than this: the firmware must shed telemetry.
    rate = XBEE_THROUGHPUT_BYTES_S if kind == "xbee" else uart_rate_bytes_s(UART_BAUD)
    runner.sim.board.link_tx_bytes_s = rate
    endpoint = SimPortEndpoint(runner.port, asyncio.get_running_loop())
    transport: Transport
    emulator: PtyUart | XBeeModule | VirtualCanNode
    if kind == "serial":
        emulator = PtyUart(endpoint, UART_BAUD, link_path=str(tmp / "ttyORB"))
        await emulator.start()
        transport = create_transport("serial", url=emulator.path, baudrate=UART_BAUD)
    elif kind == "xbee":
        emulator = XBeeModule(endpoint, 2, UART_BAUD, link_path=str(tmp / "ttyXB"))
        await emulator.start()
        transport = create_transport(
            "xbee", url=emulator.path, dest_addr64=CONTROLLER_ADDR64,
            baudrate=UART_BAUD, api_mode=2,
        )  # fmt: skip
    else:
        channel = f"orbitar-conf-{uuid.uuid4().hex}"
        emulator = VirtualCanNode(endpoint, channel)
        await emulator.start()
        transport = create_transport("can", interface="virtual", channel=channel)
    runner.start()
    try:
        yield runner, transport
    finally:
        await emulator.stop()
        runner.stop()
