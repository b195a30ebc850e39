"""The controller's CAN node, on python-can's in-process virtual bus or behind an slcan adapter.

`CanDeviceNode` is what the C firmware's CAN driver does: reassemble host frames from segments
(id 0x200 + node) for the device endpoint and segment the device's 0x00-delimited frames onto
id 0x280 + node, using `protocol.can_segments`. Frame times follow the bitrate roughly
(47 overhead bits + 8 per data byte, plus ~20 % stuffing); faults act per CAN frame: a lost
frame is a receiver overrun, a corrupted one is caught by the CAN CRC and resent by the hardware
after one more frame time.

Two fronts carry the node's CAN frames:
- `VirtualCanNode`: a python-can `virtual` bus in this process (unique channel per test);
  `disconnect` puts a bus-off error frame on the bus and goes silent.
- `SlcanAdapter`: a LAWICEL/slcan serial CAN adapter on a pty, so python-can's `slcan` interface
  (in this or another process) opens `/dev/pts/N` and reaches the node with no network at all;
  `disconnect` removes the pty, as an unplugged USB adapter would.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass

import can

from hil_sim.links.endpoint import ByteEndpoint, FrameSplitter
from hil_sim.links.faults import FaultConfig, FaultInjector
from hil_sim.links.pacing import PacedPipe
from hil_sim.links.pty_uart import PtyPort
from protocol.can_segments import (
    CAN_ERR_BUSOFF,
    CLASSIC_DATA_BYTES,
    DEFAULT_BITRATE,
    Reassembler,
    Segmenter,
    ids_for,
)

FRAME_OVERHEAD_BITS = 47
STUFFING_FACTOR = 1.2
MAX_DEVICE_FRAME_BYTES = 256  # longer runs without a delimiter are noise, not frames
SLCAN_OK = b"\r"
SLCAN_ERROR = b"\x07"
SLCAN_VERSION = "V1013"
SLCAN_SERIAL = "NORB1"
SLCAN_BITRATES = {f"S{i}": r for i, r in enumerate((10, 20, 50, 100, 125, 250, 500, 800, 1000))}


def frame_bits(data_len: int) -> int:
    """Approximate bits on the wire of a classic CAN frame with `data_len` bytes."""
    return int((FRAME_OVERHEAD_BITS + 8 * data_len) * STUFFING_FACTOR)


@dataclass
class NodeCounters:
    """Per-node traffic."""

    can_in: int = 0
    can_out: int = 0
    frames_to_device: int = 0
    frames_from_device: int = 0
    crc_resends: int = 0
    frames_damaged: int = 0  # device frames with at least one segment lost on the bus
    foreign: int = 0


class CanDeviceNode:
    """Segmenting and reassembling for the device endpoint, with bit timing and faults."""

    def __init__(
        self,
        endpoint: ByteEndpoint,
        send_payload: Callable[[int, bytes], None],
        node_id: int = 1,
        bitrate: int = DEFAULT_BITRATE,
        faults: FaultConfig | None = None,
    ) -> None:
        self.endpoint = endpoint
        self.rx_id, self.tx_id = ids_for(node_id)  # rx: host → us, tx: us → host
        self.faults = FaultInjector(faults or FaultConfig())
        self.counters = NodeCounters()
        self.reassembler = Reassembler()
        self._segmenter = Segmenter(CLASSIC_DATA_BYTES)
        self._splitter = FrameSplitter(MAX_DEVICE_FRAME_BYTES)
        self._send_payload = send_payload
        # Rates in bits per second with costs in bits: the pipe only needs consistent units.
        self._down: PacedPipe[bytes] = PacedPipe(self._arrive, bitrate)
        self._up: PacedPipe[bytes] = PacedPipe(self._emit, bitrate)

    def set_bitrate(self, bitrate: int) -> None:
        """The bus runs at a new bit rate (an adapter's S command)."""
        self._down.set_rate(bitrate)
        self._up.set_rate(bitrate)

    def start(self) -> None:
        """Connect the device and start the bus timing."""
        self._down.start()
        self._up.start()
        self.endpoint.set_sink(self._from_device)

    async def stop(self) -> None:
        """Disconnect the device; frames on the bus are lost."""
        self.endpoint.set_sink(None)
        await self._down.stop()
        await self._up.stop()

    def on_can(self, arbitration_id: int, payload: bytes) -> None:
        """A CAN frame seen on the bus."""
        if arbitration_id != self.rx_id:
            self.counters.foreign += 1
            return
        self.counters.can_in += 1
        self._through_faults(self._down, payload)

    def _from_device(self, data: bytes) -> None:
        """Device bytes → frames → segments onto the bus."""
        for frame in self._splitter.feed(data):
            self.counters.frames_from_device += 1
            lost_before = self.faults.counters.lost
            for payload in self._segmenter.split(frame):
                self._through_faults(self._up, payload)
            if self.faults.counters.lost != lost_before:
                self.counters.frames_damaged += 1

    def _through_faults(self, pipe: PacedPipe[bytes], payload: bytes) -> None:
        """A frame on the wire: lost, resent after a CRC error, or through first time."""
        bits = frame_bits(len(payload))
        out = self.faults.transmit(payload)
        if out is None:
            return
        if out != payload:
            self.counters.crc_resends += 1
            bits *= 2
        pipe.push(payload, bits, self.faults.delay_s())

    def _arrive(self, payload: bytes) -> None:
        """A host segment received: reassemble and hand whole frames to the device."""
        frame = self.reassembler.feed(payload, time.monotonic())
        if frame is not None:
            self.counters.frames_to_device += 1
            self.endpoint.write(frame)

    def _emit(self, payload: bytes) -> None:
        """Our segment's turn on the bus."""
        self.counters.can_out += 1
        self._send_payload(self.tx_id, payload)


class VirtualCanNode:
    """The node on python-can's `virtual` bus, in this process."""

    def __init__(
        self,
        endpoint: ByteEndpoint,
        channel: str,
        node_id: int = 1,
        bitrate: int = DEFAULT_BITRATE,
        faults: FaultConfig | None = None,
    ) -> None:
        self.channel = channel
        self.node = CanDeviceNode(endpoint, self._send, node_id, bitrate, faults)
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self.bus_off = False

    async def start(self) -> None:
        """Join the virtual bus."""
        loop = asyncio.get_running_loop()
        self._bus = can.Bus(interface="virtual", channel=self.channel)
        self._notifier = can.Notifier(self._bus, [self._on_message], 0.05, loop)
        self.node.start()

    async def stop(self) -> None:
        """Leave the bus."""
        await self.node.stop()
        loop = asyncio.get_running_loop()
        if self._notifier is not None:
            await loop.run_in_executor(None, self._notifier.stop)
            self._notifier = None
        if self._bus is not None:
            self._bus.shutdown()
            self._bus = None

    async def disconnect(self) -> None:
        """Bus-off: an error frame says so, then the node neither sends nor listens."""
        self.node.faults.note_disconnect()
        self.bus_off = True
        if self._bus is not None:
            error = can.Message(is_error_frame=True, arbitration_id=CAN_ERR_BUSOFF, dlc=8)
            self._bus.send(error)

    async def reconnect(self) -> None:
        """Recovered from bus-off (128 × 11 recessive bits, as the hardware does)."""
        self.bus_off = False
        self.node.reassembler.reset()

    def _on_message(self, msg: can.Message) -> None:
        """Notifier callback on the loop."""
        if not self.bus_off and not msg.is_error_frame:
            self.node.on_can(msg.arbitration_id, bytes(msg.data))

    def _send(self, arbitration_id: int, payload: bytes) -> None:
        """Put a segment on the bus."""
        if self._bus is not None and not self.bus_off:
            msg = can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False)
            self._bus.send(msg)


class SlcanAdapter:
    """A LAWICEL (slcan) USB-CAN adapter on a pty with the node on its CAN side."""

    def __init__(
        self,
        endpoint: ByteEndpoint,
        node_id: int = 1,
        bitrate: int = DEFAULT_BITRATE,
        faults: FaultConfig | None = None,
        link_path: str | None = None,
    ) -> None:
        self.node = CanDeviceNode(endpoint, self._send, node_id, bitrate, faults)
        self.port = PtyPort(self._on_serial, link_path)
        self.channel_open = False
        self.bitrate_kbps: int | None = None
        self.commands: dict[str, int] = {}
        self.errors = 0
        self._line = bytearray()

    @property
    def path(self) -> str:
        """What python-can's slcan interface opens."""
        return self.port.path

    async def start(self) -> None:
        """Plug the adapter in."""
        self.port.open()
        self.node.start()

    async def stop(self) -> None:
        """Unplug for good."""
        await self.node.stop()
        self.port.close()
        self.port.remove_link()

    async def disconnect(self) -> None:
        """Unplug the adapter: the host's serial port fails."""
        self.node.faults.note_disconnect()
        self.port.close()
        self.channel_open = False
        self._line.clear()

    async def reconnect(self) -> None:
        """Plug it back in behind the same symlink."""
        self.node.reassembler.reset()
        self.port.open()

    def _on_serial(self, data: bytes) -> None:
        """ASCII commands from the host, each ended by CR."""
        for byte in data:
            if byte == 0x0D:
                line, self._line = self._line.decode("ascii", "replace"), bytearray()
                self.port.write(self._command(line))
            elif byte != 0x0A and len(self._line) < 64:
                self._line.append(byte)

    def _command(self, line: str) -> bytes:
        """One LAWICEL command → its reply (CR, a value + CR, or BELL on error)."""
        key = line[:1]
        self.commands[key] = self.commands.get(key, 0) + 1
        with contextlib.suppress(ValueError, IndexError):
            reply = self._dispatch(key, line)
            if reply is not None:
                return reply
        self.errors += 1
        return SLCAN_ERROR

    def _dispatch(self, key: str, line: str) -> bytes | None:
        """None means the command was refused."""
        if key in "OL" and line in ("O", "L") and self.bitrate_kbps is not None:
            self.channel_open = True
            return SLCAN_OK
        if line == "C":
            self.channel_open = False
            return SLCAN_OK
        if line in SLCAN_BITRATES and not self.channel_open:
            self.bitrate_kbps = SLCAN_BITRATES[line]
            self.node.set_bitrate(self.bitrate_kbps * 1000)
            return SLCAN_OK
        if line == "V":
            return f"{SLCAN_VERSION}\r".encode()
        if line == "N":
            return f"{SLCAN_SERIAL}\r".encode()
        if line == "F":
            return b"F00\r"
        if key == "t" and self.channel_open:
            self._host_frame(line)
            return b"z\r"
        return None

    def _host_frame(self, line: str) -> None:
        """tIIILDD… → a CAN frame from the host onto the bus."""
        can_id, dlc = int(line[1:4], 16), int(line[4])
        data = bytes.fromhex(line[5 : 5 + 2 * dlc])
        if len(data) != dlc or dlc > 8:
            raise ValueError(f"bad frame {line!r}")
        self.node.on_can(can_id, data)

    def _send(self, arbitration_id: int, payload: bytes) -> None:
        """A frame from the bus to the host, if the channel is open."""
        if self.channel_open:
            self.port.write(
                f"t{arbitration_id:03X}{len(payload)}{payload.hex().upper()}\r".encode()
            )
