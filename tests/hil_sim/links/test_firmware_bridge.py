"""The link emulators in front of the real firmware mirror, run by the real-time runner."""

from __future__ import annotations

import asyncio
import threading
import uuid
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from hil_sim.links.can_node import VirtualCanNode
from hil_sim.links.endpoint import SimPortEndpoint, build
from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.xbee import CONTROLLER_ADDR64, XBeeModule
from host.transport import Transport, create_transport
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, encode_frame
from protocol.messages import Hello, Identify
from tests.transport.harness import Collector

runner_mod = pytest.importorskip("hil_sim.runner")


class _ThreadPort:
    """A stand-in port that delivers from a foreign thread, as the runner does."""

    def __init__(self) -> None:
        self.written: list[bytes] = []
        self.receiver: Any = None

    def write_to_firmware(self, data: bytes) -> None:
        self.written.append(data)

    def set_receiver(self, receiver: Any) -> None:
        self.receiver = receiver


async def test_sim_port_endpoint_hops_threads() -> None:
    port = _ThreadPort()
    endpoint = SimPortEndpoint(port, asyncio.get_running_loop())
    got: list[bytes] = []
    endpoint.set_sink(got.append)
    endpoint.write(b"abc")
    thread = threading.Thread(target=port.receiver, args=(b"xyz",))
    thread.start()
    thread.join()
    await asyncio.sleep(0.01)
    assert port.written == [b"abc"]
    assert got == [b"xyz"]
    endpoint.set_sink(None)
    assert port.receiver is None


@pytest.fixture
async def firmware() -> AsyncIterator[SimPortEndpoint]:
    """The firmware mirror and plant in real time, behind a loop-side endpoint."""
    runner = runner_mod.RealtimeRunner(runner_mod.Simulation())
    runner.start()
    try:
        yield SimPortEndpoint(runner.port, asyncio.get_running_loop())
    finally:
        await asyncio.get_running_loop().run_in_executor(None, runner.stop)


async def _hello_identify(transport: Transport) -> None:
    """HELLO to the firmware; its IDENTIFY must come back."""
    rx = Collector()
    rx.attach(transport)
    await transport.open()
    try:
        transport.send(encode_frame(build(Hello, PROTOCOL_VERSION, SCHEMA_HASH), 1))
        packets = await rx.wait_packets(1, timeout_s=5.0)
        identify = [p.message for p in packets if isinstance(p.message, Identify)]
        assert identify, f"no IDENTIFY among {packets}"
        assert getattr(identify[0], "req_seq") == 1  # noqa: B009
    finally:
        await transport.close()


async def test_firmware_over_pty_uart(firmware: SimPortEndpoint, tmp_path: Path) -> None:
    uart = PtyUart(firmware, 115200, link_path=str(tmp_path / "tty"))
    await uart.start()
    try:
        await _hello_identify(create_transport("serial", url=uart.path))
    finally:
        await uart.stop()


async def test_firmware_over_xbee(firmware: SimPortEndpoint, tmp_path: Path) -> None:
    module = XBeeModule(firmware, api_mode=2, link_path=str(tmp_path / "xbee"))
    await module.start()
    try:
        transport = create_transport(
            "xbee", url=module.path, dest_addr64=CONTROLLER_ADDR64, baudrate=115200, api_mode=2
        )
        await _hello_identify(transport)
    finally:
        await module.stop()


async def test_firmware_over_virtual_can(firmware: SimPortEndpoint) -> None:
    channel = f"fw-{uuid.uuid4().hex}"
    node = VirtualCanNode(firmware, channel)
    await node.start()
    try:
        await _hello_identify(create_transport("can", interface="virtual", channel=channel))
    finally:
        await node.stop()
