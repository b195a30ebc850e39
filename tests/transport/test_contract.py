"""The transport contract, run back to back against every backend and its link emulator."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from hil_sim.links.endpoint import build
from hil_sim.links.faults import FaultConfig
from host.transport import FrameTooLargeError, Transport, TransportError, TransportState
from protocol import PROTOCOL_VERSION, SCHEMA_HASH, Packet, encode_frame
from protocol.messages import EncoderSample, Heartbeat, Hello, Identify
from tests.transport.harness import (
    Collector,
    Link,
    PtySerialLink,
    SlcanLink,
    TcpSerialLink,
    VirtualCanLink,
    XBeeMode1Link,
    XBeeMode2Link,
)

TELEMETRY_FRAMES = 150
LOST_TIMEOUT_S = 3.0
MAX_FRAME_BYTES = 84


def value(packet: Packet, name: str) -> int:
    """A field of a decoded message (messages are typed `object` by the decoder)."""
    return int(getattr(packet.message, name))


def hello(seq: int) -> bytes:
    """A HELLO wire frame."""
    return encode_frame(build(Hello, PROTOCOL_VERSION, SCHEMA_HASH), seq)


def heartbeat(seq: int) -> bytes:
    """A HEARTBEAT wire frame."""
    return encode_frame(build(Heartbeat, seq * 10), seq)


async def send_telemetry(link: Link, n: int) -> None:
    """The controller streams n encoder samples, spaced so no line saturates."""
    for i in range(n):
        link.controller.send_sample(i * 1000)
        await asyncio.sleep(link.frame_gap_s)


class TransportContract:
    """Every backend moves whole frames, keeps statistics, survives unplug and reopens."""

    link_cls: Callable[..., Link]

    @pytest.fixture
    async def link(self, tmp_path: Path) -> AsyncIterator[Link]:
        """A started emulator with a fake controller."""
        link = self.link_cls(tmp_path)
        await link.start()
        yield link
        await link.stop()

    @pytest.fixture
    async def opened(self, link: Link) -> AsyncIterator[tuple[Transport, Collector]]:
        """An opened host transport with a collecting receiver."""
        transport = link.transport()
        collector = Collector()
        collector.attach(transport)
        await transport.open()
        yield transport, collector
        await transport.close()

    async def test_hello_is_answered_with_identify(
        self, opened: tuple[Transport, Collector]
    ) -> None:
        transport, rx = opened
        transport.send(hello(7))
        packets = await rx.wait_packets(1)
        assert len(packets) == 1
        assert isinstance(packets[0].message, Identify)
        assert value(packets[0], "req_seq") == 7
        assert transport.stats.frames_out == 1
        assert transport.stats.bytes_out == len(hello(7))
        assert transport.stats.bytes_in > 0

    async def test_frames_arrive_whole_and_in_order(
        self, link: Link, opened: tuple[Transport, Collector]
    ) -> None:
        transport, rx = opened
        for seq in range(40):
            transport.send(heartbeat(seq))
            if seq % 8 == 7:  # bursts a radio module's buffer holds
                await asyncio.sleep(8 * link.frame_gap_s)
        packets = await rx.wait_packets(40, timeout_s=10.0)
        assert [value(p, "uptime_ms") for p in packets] == [s * 10 for s in range(40)]
        assert rx.decoder.drops.total() == 0
        assert [p.seq for p in link.controller.received] == list(range(40))

    async def test_telemetry_stream_without_faults_is_complete(
        self, link: Link, opened: tuple[Transport, Collector]
    ) -> None:
        _, rx = opened
        await send_telemetry(link, TELEMETRY_FRAMES)
        packets = await rx.wait_packets(TELEMETRY_FRAMES, timeout_s=10.0)
        assert [p.seq for p in packets] == list(range(TELEMETRY_FRAMES))
        assert all(isinstance(p.message, EncoderSample) for p in packets)

    async def test_largest_frame_passes_and_larger_is_refused_where_limited(
        self, link: Link, opened: tuple[Transport, Collector]
    ) -> None:
        transport, rx = opened
        link.controller.echo_raw = True
        frame = bytes(range(1, MAX_FRAME_BYTES)) + b"\x00"
        transport.send(frame)
        await rx.wait_packets(0, timeout_s=0.0)
        await _wait_bytes(rx, MAX_FRAME_BYTES)
        assert b"".join(rx.chunks) == frame
        limit = transport.max_frame_bytes
        if limit is not None:
            assert limit == MAX_FRAME_BYTES
            with pytest.raises(FrameTooLargeError):
                transport.send(b"\x01" * limit + b"\x00")
            assert transport.state is TransportState.OPEN
            assert transport.stats.extra["oversize_refused"] == 1

    async def test_close_then_reopen(self, link: Link) -> None:
        transport = link.transport()
        rx = Collector()
        rx.attach(transport)
        for round_ in range(2):
            await transport.open()
            transport.send(hello(round_))
            await rx.wait_packets(round_ + 1)
            await transport.close()
            assert transport.state is TransportState.CLOSED
            with pytest.raises(TransportError):
                transport.send(hello(9))
        assert [value(p, "req_seq") for p in rx.packets] == [0, 1]
        assert transport.stats.opens == 2
        await transport.close()  # twice is fine

    async def test_unplug_reports_lost_and_reopen_works(self, link: Link) -> None:
        transport = link.transport()
        rx = Collector()
        rx.attach(transport)
        await transport.open()
        try:
            await link.disconnect()
            await asyncio.wait_for(rx.lost.wait(), LOST_TIMEOUT_S)
            assert transport.state is TransportState.LOST
            assert transport.stats.losses == 1
            await transport.close()
            await link.reconnect()
            await transport.open()
            transport.send(hello(3))
            packets = await rx.wait_packets(1)
            assert [value(p, "req_seq") for p in packets] == [3]
        finally:
            await transport.close()

    async def test_injected_losses_match_what_arrives(self, tmp_path: Path) -> None:
        faults = FaultConfig(drop_rate=0.15, burst_rate=0.02, burst_length_mean=3.0, seed=11)
        link = self.link_cls(tmp_path, faults_to_host=faults)
        await link.start()
        transport = link.transport()
        rx = Collector()
        rx.attach(transport)
        await transport.open()
        try:
            await send_telemetry(link, TELEMETRY_FRAMES)
            # The emulator decides every loss as it sends, so the count due is known now.
            lost = link.frames_lost_to_host()
            await rx.wait_packets(TELEMETRY_FRAMES - lost, timeout_s=15.0)
            await rx.settle(quiet_s=0.1)  # anything beyond the count due would show up here
            injected = link.injected_to_host()
            assert injected.lost > 0
            assert len(rx.packets) == TELEMETRY_FRAMES - lost
            seqs = [p.seq for p in rx.packets]
            assert seqs == sorted(set(seqs))
            assert rx.decoder.drops.total() == 0
            _check_backend_counters(link, transport)
        finally:
            await transport.close()
            await link.stop()


def _check_backend_counters(link: Link, transport: Transport) -> None:
    """Backend statistics agree with what the emulator injected."""
    extra = transport.stats.extra
    if isinstance(link, XBeeMode1Link | XBeeMode2Link):
        assert extra.get("xbee_rx_packets", 0) == link.emulator.counters.rx_packets
    if isinstance(link, VirtualCanLink | SlcanLink):
        lost = link.injected_to_host().lost
        # A loss in the last segments sent is invisible until more traffic comes.
        assert lost - 12 <= extra.get("can_lost_segments", 0) <= lost
        assert extra.get("can_frames_delivered", 0) == TELEMETRY_FRAMES - link.frames_lost_to_host()


async def _wait_bytes(rx: Collector, n: int, timeout_s: float = 3.0) -> None:
    """Wait until n bytes were delivered."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while sum(map(len, rx.chunks)) < n and loop.time() < deadline:
        await asyncio.sleep(0.01)


class TestSerialPty(TransportContract):
    link_cls = PtySerialLink


class TestSerialSocket(TransportContract):
    link_cls = TcpSerialLink


class TestXBeeApiMode1(TransportContract):
    link_cls = XBeeMode1Link


class TestXBeeApiMode2(TransportContract):
    link_cls = XBeeMode2Link


class TestCanVirtual(TransportContract):
    link_cls = VirtualCanLink


class TestCanSlcan(TransportContract):
    link_cls = SlcanLink
