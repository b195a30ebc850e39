"""CAN link: wire frames segmented over classic CAN (or CAN FD) frames with python-can.

Any python-can interface by name (socketcan, slcan, pcan, kvaser, virtual …). Host → controller
frames use the 11-bit id 0x200 + node_id, controller → host 0x280 + node_id; the segment header
is described in `can_segments`. python-can's Bus is blocking, so receiving is event driven: a bus
with a file descriptor (socketcan, slcan) is watched with the loop's `add_reader` and read with
`recv(0)`; one without (virtual, most vendor drivers) gets a `can.Notifier` thread that hands
messages to the loop. Bus errors and a bus-off error frame end the link with `_lost`.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from typing import Any, ClassVar

import can

from host.transport.base import Transport, TransportError
from protocol.can_segments import (
    CAN_ERR_BUSOFF,
    CLASSIC_DATA_BYTES,
    DEFAULT_BITRATE,
    FD_DATA_BYTES,
    Reassembler,
    Segmenter,
    check_node_id,
    ids_for,
)

NOTIFIER_POLL_S = 0.05  # how long the Notifier thread blocks in recv: bounds close() latency


class _ErrorListener(can.Listener):
    """Notifier listener: messages and reader-thread errors, already on the loop thread."""

    def __init__(self, owner: CanTransport) -> None:
        self._owner = owner

    def on_message_received(self, msg: can.Message) -> None:
        """A CAN frame from the bus."""
        self._owner._on_can_message(msg)

    def on_error(self, exc: Exception) -> None:
        """The reader thread died: the bus is gone."""
        self._owner._on_bus_error(exc)


class CanTransport(Transport):
    """Wire frames over CAN with a one-byte segment header per CAN frame."""

    scheme: ClassVar[str] = "can"

    def __init__(
        self,
        interface: str,
        channel: str | int,
        node_id: int = 1,
        bitrate: int = DEFAULT_BITRATE,
        fd: bool = False,
        **bus_options: Any,
    ) -> None:
        super().__init__()
        if not isinstance(interface, str) or interface not in can.VALID_INTERFACES:
            raise ValueError(f"interface {interface!r} is not a python-can interface")
        if isinstance(bitrate, bool) or not isinstance(bitrate, int) or bitrate <= 0:
            raise ValueError(f"bitrate must be a positive integer, got {bitrate!r}")
        self.interface = interface
        self.channel = channel
        self.node_id = check_node_id(node_id)
        self.tx_id, self.rx_id = ids_for(self.node_id)
        self.bitrate = bitrate
        self.fd = bool(fd)
        self._bus_options = bus_options
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._fd_watched: int | None = None
        self._segmenter = Segmenter(FD_DATA_BYTES if self.fd else CLASSIC_DATA_BYTES)
        self._reassembler = Reassembler()

    def describe(self) -> str:
        """E.g. 'can slcan:/dev/pts/3 node 1 @500000'."""
        return f"can {self.interface}:{self.channel} node {self.node_id} @{self.bitrate}"

    def resync(self) -> None:
        """A restarted controller restarts its segment counter: drop any partial frame."""
        self._reassembler.reset()

    async def _open(self) -> None:
        """Create the bus off the loop (drivers block) and start receiving."""
        loop = asyncio.get_running_loop()
        self.resync()
        try:
            bus = await loop.run_in_executor(None, self._make_bus)
        except (can.CanError, ImportError) as exc:
            raise TransportError(f"{self.describe()}: {exc}") from exc
        self._bus = bus
        try:
            fileno = bus.fileno()
        except (NotImplementedError, OSError):
            fileno = -1
        if fileno >= 0:
            loop.add_reader(fileno, self._drain)
            self._fd_watched = fileno
        else:
            self._notifier = can.Notifier(bus, [_ErrorListener(self)], NOTIFIER_POLL_S, loop)

    def _make_bus(self) -> can.BusABC:
        """The blocking part of opening."""
        return can.Bus(
            interface=self.interface,
            channel=self.channel,
            bitrate=self.bitrate,
            fd=self.fd,
            **self._bus_options,
        )

    def _write(self, frame: bytes) -> None:
        """Segment the frame and put every piece on the bus."""
        bus = self._bus
        if bus is None:
            raise OSError("bus is closed")
        for payload in self._segmenter.split(frame):
            msg = can.Message(
                arbitration_id=self.tx_id, data=payload, is_extended_id=False, is_fd=self.fd
            )
            try:
                bus.send(msg)
            except can.CanError as exc:
                raise OSError(f"CAN send failed: {exc}") from exc
            self.stats.bump("can_frames_out")

    async def _close(self) -> None:
        """Stop receiving and shut the bus down off the loop."""
        await self._release(asyncio.get_running_loop())

    async def _release(self, loop: asyncio.AbstractEventLoop) -> None:
        """Undo `_open`, whatever state it got to."""
        bus, notifier, fileno = self._bus, self._notifier, self._fd_watched
        self._bus, self._notifier, self._fd_watched = None, None, None
        if fileno is not None:
            loop.remove_reader(fileno)
        if notifier is not None:
            await loop.run_in_executor(None, notifier.stop)
        if bus is not None:
            await loop.run_in_executor(None, self._shutdown_quietly, bus)

    @staticmethod
    def _shutdown_quietly(bus: can.BusABC) -> None:
        """Shut a bus down; a bus already dead cannot be shut down and need not be."""
        with contextlib.suppress(can.CanError, OSError):
            bus.shutdown()

    def _drain(self) -> None:
        """add_reader callback: read every complete CAN frame waiting on the descriptor."""
        bus = self._bus
        while bus is not None:
            try:
                msg = bus.recv(0)
            except (can.CanError, OSError, ValueError) as exc:
                self._on_bus_error(exc)
                return
            if msg is None:
                return
            self._on_can_message(msg)
            bus = self._bus

    def _on_bus_error(self, exc: Exception) -> None:
        """The bus failed: stop watching it and report the link lost."""
        if self._fd_watched is not None:
            asyncio.get_running_loop().remove_reader(self._fd_watched)
            self._fd_watched = None
        self.stats.bump("can_bus_errors")
        self._lost(exc)

    def _on_can_message(self, msg: can.Message) -> None:
        """One CAN frame: error frames are counted, ours are reassembled."""
        if msg.is_error_frame:
            self._on_error_frame(msg)
            return
        if msg.arbitration_id != self.rx_id or msg.is_extended_id or msg.is_remote_frame:
            self.stats.bump("can_foreign_frames")
            return
        frame = self._reassembler.feed(bytes(msg.data), time.monotonic())
        self.stats.extra.update(self._reassembler.stats.as_dict())
        if frame is not None:
            self._deliver(frame)

    def _on_error_frame(self, msg: can.Message) -> None:
        """Bus-off ends the link; other error frames are only counted."""
        self.stats.bump("can_error_frames")
        if msg.arbitration_id & CAN_ERR_BUSOFF:
            self._on_bus_error(TransportError(f"{self.describe()}: bus off"))
