"""One emulated link per transport, with the fake controller at the device end."""

from __future__ import annotations

import abc
import asyncio
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil_sim.links.can_node import SlcanAdapter, VirtualCanNode
from hil_sim.links.endpoint import FakeController
from hil_sim.links.faults import FaultConfig, FaultCounters
from hil_sim.links.pty_uart import PtyUart
from hil_sim.links.tcp import TcpLink
from hil_sim.links.xbee import CONTROLLER_ADDR64, XBeeModule
from host.transport import Transport, create_transport
from protocol import FrameDecoder, Packet

UART_BAUD = 115200


class Link(abc.ABC):
    """An emulator, its controller and a factory for the host transport that reaches it."""

    name = "link"
    datagram_unit = True  # each fault unit towards the host is exactly one wire frame
    # Spacing of frames sent in a row, so that a stream stays within what the link carries.
    frame_gap_s = 0.002

    def __init__(self, tmp: Path, faults_to_host: FaultConfig | None = None) -> None:
        self.tmp = tmp
        self.controller = FakeController()
        self.faults_to_host = faults_to_host
        self.emulator: Any = None

    @abc.abstractmethod
    def build(self) -> Any:
        """Create the emulator."""

    @abc.abstractmethod
    def transport(self) -> Transport:
        """A host transport for this link."""

    @abc.abstractmethod
    def injected_to_host(self) -> FaultCounters:
        """Fault counters of the controller → host direction."""

    def frames_lost_to_host(self) -> int:
        """Wire frames the emulator lost towards the host."""
        return self.injected_to_host().lost

    async def start(self) -> None:
        """Start the emulator."""
        self.emulator = self.build()
        await self.emulator.start()

    async def stop(self) -> None:
        """Stop the emulator."""
        await self.emulator.stop()

    async def disconnect(self) -> None:
        """Unplug."""
        await self.emulator.disconnect()

    async def reconnect(self) -> None:
        """Plug back in."""
        await self.emulator.reconnect()


class PtySerialLink(Link):
    """pyserial on a real pty at 115200 baud."""

    name = "serial-pty"

    def build(self) -> PtyUart:
        """A paced pty UART."""
        link = str(self.tmp / "ttyORB")
        return PtyUart(
            self.controller, UART_BAUD, faults_to_host=self.faults_to_host, link_path=link
        )

    def transport(self) -> Transport:
        """Serial transport on the stable pty link."""
        return create_transport("serial", url=self.emulator.path, baudrate=UART_BAUD)

    def injected_to_host(self) -> FaultCounters:
        """Counters of the pty's upward line."""
        return self.emulator.to_host.counters  # type: ignore[no-any-return]


class TcpSerialLink(Link):
    """pyserial's socket:// to 127.0.0.1."""

    name = "serial-socket"

    def build(self) -> TcpLink:
        """A loopback TCP server."""
        return TcpLink(self.controller, faults_to_host=self.faults_to_host)

    def transport(self) -> Transport:
        """Serial transport by URL."""
        return create_transport("serial", url=self.emulator.url)

    def injected_to_host(self) -> FaultCounters:
        """Counters of the upward direction."""
        return self.emulator.to_host.counters  # type: ignore[no-any-return]


class XBeeLink(Link):
    """XBee API frames over a pty to the emulated module pair."""

    api_mode = 1
    # The air carries ~100 encoder frames a second in all, retries included, and a module buffers
    # only 202 bytes (7 such frames): faster, frames are lost in the module.
    frame_gap_s = 0.016

    def build(self) -> XBeeModule:
        """The module emulation."""
        return XBeeModule(
            self.controller,
            api_mode=self.api_mode,
            uart_baud=UART_BAUD,
            air_faults=self.faults_to_host,
            link_path=str(self.tmp / "ttyXBEE"),
        )

    def transport(self) -> Transport:
        """XBee transport to the controller's module."""
        return create_transport(
            "xbee",
            url=self.emulator.path,
            dest_addr64=CONTROLLER_ADDR64,
            baudrate=UART_BAUD,
            api_mode=self.api_mode,
        )

    def injected_to_host(self) -> FaultCounters:
        """Air faults towards the host (per attempt)."""
        return self.emulator.air_up.counters  # type: ignore[no-any-return]

    def frames_lost_to_host(self) -> int:
        """MAC retries hide most air losses; only exhausted ones lose a frame."""
        return int(self.emulator.counters.up_lost)


class XBeeMode1Link(XBeeLink):
    """AP=1."""

    name = "xbee-ap1"


class XBeeMode2Link(XBeeLink):
    """AP=2, escaped."""

    name = "xbee-ap2"
    api_mode = 2


class CanLink(Link):
    """Common CAN accounting: a frame is lost when any of its segments is."""

    datagram_unit = False

    def injected_to_host(self) -> FaultCounters:
        """Per CAN frame."""
        return self.emulator.node.faults.counters  # type: ignore[no-any-return]

    def frames_lost_to_host(self) -> int:
        """Frames with at least one segment lost."""
        return int(self.emulator.node.counters.frames_damaged)


class VirtualCanLink(CanLink):
    """python-can's in-process virtual bus."""

    name = "can-virtual"

    def __init__(self, tmp: Path, faults_to_host: FaultConfig | None = None) -> None:
        super().__init__(tmp, faults_to_host)
        self.channel = f"orbitar-{uuid.uuid4().hex}"

    def build(self) -> VirtualCanNode:
        """The node on its own virtual channel."""
        return VirtualCanNode(self.controller, self.channel, faults=self.faults_to_host)

    def transport(self) -> Transport:
        """CAN transport on the same channel."""
        return create_transport("can", interface="virtual", channel=self.channel)


class SlcanLink(CanLink):
    """python-can's slcan interface on a pty served by the emulated adapter."""

    name = "can-slcan"

    def build(self) -> SlcanAdapter:
        """The adapter."""
        link = str(self.tmp / "ttySLCAN")
        return SlcanAdapter(self.controller, faults=self.faults_to_host, link_path=link)

    def transport(self) -> Transport:
        """CAN transport through the adapter."""
        return create_transport(
            "can", interface="slcan", channel=self.emulator.path, sleep_after_open=0
        )


ALL_LINKS: list[Callable[..., Link]] = [
    PtySerialLink,
    TcpSerialLink,
    XBeeMode1Link,
    XBeeMode2Link,
    VirtualCanLink,
    SlcanLink,
]


class Collector:
    """Host-side receiver: decodes what the transport delivers and records lost news."""

    def __init__(self) -> None:
        self.decoder = FrameDecoder()
        self.packets: list[Packet] = []
        self.chunks: list[bytes] = []
        self.lost = asyncio.Event()
        self.lost_exc: Exception | None = None
        self._arrived = asyncio.Event()

    def attach(self, transport: Transport) -> None:
        """Become the transport's receiver."""
        transport.set_receiver(self.on_bytes, self.on_lost)

    def on_bytes(self, data: bytes) -> None:
        """Receiver callback."""
        self.chunks.append(data)
        self.packets += self.decoder.feed(data)
        self._arrived.set()

    def on_lost(self, exc: Exception | None) -> None:
        """Lost callback."""
        self.lost_exc = exc
        self.lost.set()

    async def wait_packets(self, n: int, timeout_s: float = 5.0) -> list[Packet]:
        """Wait until at least n packets arrived (or time out and return what there is)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while len(self.packets) < n and loop.time() < deadline:
            self._arrived.clear()
            try:
                await asyncio.wait_for(self._arrived.wait(), deadline - loop.time())
            except TimeoutError:
                break
        return self.packets

    async def settle(self, quiet_s: float = 0.3, timeout_s: float = 10.0) -> None:
        """Wait until nothing has arrived for `quiet_s`."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while loop.time() < deadline:
            self._arrived.clear()
            try:
                await asyncio.wait_for(self._arrived.wait(), quiet_s)
            except TimeoutError:
                return
