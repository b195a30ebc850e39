"""CAN backend details the contract does not cover: ids, CAN FD, foreign and error frames."""

from __future__ import annotations

import asyncio
import uuid
from collections.abc import AsyncIterator

import can
import pytest

from hil_sim.links.can_node import VirtualCanNode
from hil_sim.links.endpoint import FakeController, build
from host.transport import Transport, TransportState, create_transport
from host.transport.can import CanTransport
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, encode_frame
from protocol.can_segments import CAN_ERR_BUSOFF, Segmenter, ids_for
from protocol.messages import Hello, Identify
from tests.transport.harness import Collector

NODE = 5


@pytest.fixture
def channel() -> str:
    """A virtual bus of this test's own."""
    return f"orbitar-{uuid.uuid4().hex}"


@pytest.fixture
async def peer(channel: str) -> AsyncIterator[can.BusABC]:
    """A raw python-can bus on the same channel, to see and forge frames."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def state_of(transport: Transport) -> TransportState:
    """The state, read through a call so the type checker does not pin it."""
    return transport.state


def test_ids() -> None:
    assert ids_for(1) == (0x201, 0x281)
    assert ids_for(127) == (0x27F, 0x2FF)


async def test_host_frames_use_the_node_id_and_segment_headers(
    channel: str, peer: can.BusABC
) -> None:
    transport = create_transport("can", interface="virtual", channel=channel, node_id=NODE)
    await transport.open()
    try:
        frame = encode_frame(build(Hello, PROTOCOL_VERSION, SCHEMA_HASH), 4)
        transport.send(frame)
        loop = asyncio.get_running_loop()
        msgs = [await loop.run_in_executor(None, peer.recv, 1.0) for _ in range(2)]
        assert all(m is not None and m.arbitration_id == 0x205 for m in msgs)
        payloads = [bytes(m.data) for m in msgs if m is not None]
        assert payloads == Segmenter().split(frame)
    finally:
        await transport.close()


async def test_foreign_and_error_frames(channel: str, peer: can.BusABC) -> None:
    transport = create_transport("can", interface="virtual", channel=channel, node_id=NODE)
    rx = Collector()
    rx.attach(transport)
    await transport.open()
    try:
        peer.send(can.Message(arbitration_id=0x286, data=b"\xc0\x01"))  # node 6 is not ours
        peer.send(can.Message(is_error_frame=True, arbitration_id=0x04, dlc=8))  # ctrl error
        good = encode_frame(build(Hello, PROTOCOL_VERSION, SCHEMA_HASH), 1)
        for payload in Segmenter().split(good):
            peer.send(can.Message(arbitration_id=0x285, data=payload, is_extended_id=False))
        await rx.wait_packets(1)
        assert transport.stats.extra["can_foreign_frames"] == 1
        assert transport.stats.extra["can_error_frames"] == 1
        assert transport.state is TransportState.OPEN
        peer.send(can.Message(is_error_frame=True, arbitration_id=CAN_ERR_BUSOFF, dlc=8))
        await asyncio.wait_for(rx.lost.wait(), 2.0)
        assert state_of(transport) is TransportState.LOST
    finally:
        await transport.close()


async def test_can_fd_segments_carry_63_bytes(channel: str) -> None:
    controller = FakeController()
    node = VirtualCanNode(controller, channel)
    await node.start()
    transport = create_transport("can", interface="virtual", channel=channel, fd=True)
    assert isinstance(transport, CanTransport)
    rx = Collector()
    rx.attach(transport)
    await transport.open()
    try:
        transport.send(encode_frame(build(Hello, PROTOCOL_VERSION, SCHEMA_HASH), 9))
        packets = await rx.wait_packets(1)
        assert isinstance(packets[0].message, Identify)
        assert transport.stats.extra["can_frames_out"] == 1  # 14 bytes in one FD frame
    finally:
        await transport.close()
        await node.stop()
