"""Two XBee modules and the air between them, seen from the host's UART.

The host talks API frames (mode 1 or 2) to a pty as it would to its own module. The emulator
unpacks Transmit Requests (0x10), refuses RF data over 84 bytes, sends the rest over the air
(timing below) with latency and loss (each failed attempt retried by the MAC up to 3 times) to
the device endpoint, and answers each request with a Transmit Status (0x8B) giving the retries
and the outcome. Bytes from the device are packetised at 0x00 frame delimiters, as the
controller's firmware hands whole frames to its module, and arrive at the host as Receive
Packets (0x90) from the controller module's 64-bit address.

Timing, against Digi's figures for XBee ZB (0x10/0x90 frames, 84-byte unicast payload):
- Digi's XBee/XBee-PRO ZB RF Modules user guide, "Throughput": 1 hop, router to router,
  security disabled, 35 kbit/s, measured sending 100,000 bytes with the serial interface at
  115200 b/s, i.e. in full 84-byte packets: 84 · 8 / 35 000 = 19.2 ms per packet.
- Digi knowledge base, "Sending data through an 802.15.4 network latency timing": 250 kbit/s
  RF rate, 32 µs per byte; best-case unicast with 16-bit addressing (as ZigBee uses)
  0.544 + 0.032·B ms. The air proper is thus a small part of those 19.2 ms; the rest is the
  stack's acknowledgements (MAC and APS) and processing, which no figure breaks down.
A packet here occupies the shared channel for (B + AIR_OVERHEAD_BYTES) · 8 / AIR_RATE_BPS at
35 kbit/s: a full packet takes 23.3 ms, 18 % slower than Digi's measured 19.2 ms, since the
measured rate already includes the overhead. Calibrated to 42.5 kbit/s (a full packet in
19.2 ms), the quick demo over XBee lost its link to heartbeat silence in 4 of 7 runs at load
10-17 (none at 35 kbit/s, 4 runs): a cause not found yet, so the model stays pessimistic there
until it is. How a short packet's cost splits between a fixed and a per-byte part is in no
figure: this model's split (4.1 ms + 0.23 ms a byte) is an assumption. Optimistic on the other
side: the controller's UART to its module is not paced (a 60-byte batch would take 5.2 ms at
115200 Bd). Pacing it was tried and left out: behind the demo's one-process loop, stalls then
burst seconds of frames into the bounded UART buffer and the link died of heartbeat silence.

The air is one half-duplex channel: both modules' packets take turns on it, so what one
direction sends is air time the other cannot use. Each module holds the data waiting for the air
in its serial receive buffer, 202 bytes on an XBee 802.15.4 module; data that arrives while it
is full is lost (neither UART here uses CTS flow control), as a real module loses it. Offered
more than the air carries, the link loses frames at once instead of queueing them for ever.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass

from hil_sim.links.endpoint import ByteEndpoint, FrameSplitter
from hil_sim.links.faults import FaultConfig, FaultInjector
from hil_sim.links.pacing import Line, PacedPipe, uart_rate_bytes_s
from hil_sim.links.pty_uart import PtyPort
from protocol.xbee_frames import (
    MAX_RF_PAYLOAD,
    ApiFrameDecoder,
    DeliveryStatus,
    FrameType,
    ReceivePacket,
    TransmitRequest,
    TransmitStatus,
    encode_api_frame,
)

CONTROLLER_ADDR64 = 0x0013A200_40A1B2C3
AIR_RATE_BPS = 35_000  # Digi's measured ZB throughput, used as the air rate (see above)
AIR_OVERHEAD_BYTES = 18  # MAC header, addresses, FCS per RF packet
AIR_LATENCY_S = 0.002
MAC_RETRIES = 3
SERIAL_BUFFER_BYTES = 202  # the module's serial receive ("DI") buffer, XBee 802.15.4


@dataclass
class ModuleCounters:
    """What the emulated module did with each frame."""

    tx_requests: int = 0
    delivered: int = 0
    failed: int = 0
    retries: int = 0
    too_large: int = 0
    wrong_address: int = 0
    unknown_frames: int = 0
    rx_packets: int = 0
    up_lost: int = 0
    down_overflow: int = 0  # Transmit Requests lost in the host's module: its buffer was full
    up_overflow: int = 0  # frames lost in the controller's module: its buffer was full


class SerialBuffer:
    """A module's serial receive buffer: RF data waiting for the air, at most `capacity` bytes.

    A packet's data stays until its last MAC attempt has left the air (it may be retried).
    """

    def __init__(self, capacity: int = SERIAL_BUFFER_BYTES) -> None:
        self.capacity = capacity
        self.peak = 0
        self._held: collections.deque[tuple[float, int]] = collections.deque()
        self._bytes = 0

    @property
    def held(self) -> int:
        """Bytes waiting for the air now."""
        self._release(time.monotonic())
        return self._bytes

    def admit(self, size: int) -> bool:
        """Whether `size` more bytes fit now."""
        return self.held + size <= self.capacity

    def hold(self, size: int, until_s: float) -> None:
        """Keep `size` bytes until monotonic time `until_s`, when their packet has left."""
        self._held.append((until_s, size))
        self._bytes += size
        self.peak = max(self.peak, self._bytes)

    def clear(self) -> None:
        """Power loss: everything held is gone."""
        self._held.clear()
        self._bytes = 0

    def _release(self, now_s: float) -> None:
        """Forget the packets that have left the air (they leave in order: one channel)."""
        while self._held and self._held[0][0] <= now_s:
            self._bytes -= self._held.popleft()[1]


@dataclass(frozen=True, slots=True)
class _AirPacket:
    """RF data on its way to the device, and the status owed to the host."""

    data: bytes
    frame_id: int
    retries: int


class XBeeModule:
    """The host's XBee (API mode on a pty) plus the air and the controller's XBee."""

    def __init__(
        self,
        endpoint: ByteEndpoint,
        api_mode: int = 1,
        uart_baud: int = 115200,
        controller_addr64: int = CONTROLLER_ADDR64,
        air_rate_bps: int = AIR_RATE_BPS,
        air_faults: FaultConfig | None = None,
        link_path: str | None = None,
        latency_s: float = AIR_LATENCY_S,
    ) -> None:
        if api_mode not in (1, 2):
            raise ValueError(f"api_mode must be 1 or 2, got {api_mode}")
        self.endpoint = endpoint
        self.escaped = api_mode == 2
        self.controller_addr64 = controller_addr64
        self.latency_s = latency_s
        base = air_faults or FaultConfig()
        self.air_down = FaultInjector(base)
        self.air_up = FaultInjector(FaultConfig(**{**vars(base), "seed": base.seed + 1}))
        self.counters = ModuleCounters()
        self.air_bytes = 0  # air time used, both ways, in bytes: every MAC attempt and overhead
        self.port = PtyPort(self._from_uart, link_path)
        self._decoder = ApiFrameDecoder(escaped=self.escaped)
        self._splitter = FrameSplitter(MAX_RF_PAYLOAD)
        air_rate = self._air_rate = air_rate_bps / 8
        air = Line()  # one channel for both directions
        self.down_buffer = SerialBuffer()  # in the host's module
        self.up_buffer = SerialBuffer()  # in the controller's module
        self._uart_in: PacedPipe[bytes] = PacedPipe(self._on_uart, uart_rate_bytes_s(uart_baud))
        self._uart_out: PacedPipe[bytes] = PacedPipe(self.port.write, uart_rate_bytes_s(uart_baud))
        self._air_down: PacedPipe[_AirPacket] = PacedPipe(self._arrive_device, air_rate, air)
        self._air_up: PacedPipe[bytes] = PacedPipe(self._arrive_host, air_rate, air)
        self._pipes = (self._uart_in, self._uart_out, self._air_down, self._air_up)

    @property
    def path(self) -> str:
        """What the host's XBee transport opens."""
        return self.port.path

    @property
    def decoder_stats(self) -> dict[str, int]:
        """The module's API parser counters (bad checksums from the host, …)."""
        return dict(vars(self._decoder.stats))

    async def start(self) -> None:
        """Power up: pty ready, device connected."""
        self.port.open()
        for pipe in self._pipes:
            pipe.start()
        self.endpoint.set_sink(self._from_device)

    async def stop(self) -> None:
        """Power down and remove the pty."""
        self.endpoint.set_sink(None)
        await self.disconnect(count=False)
        self.port.remove_link()

    async def disconnect(self, count: bool = True) -> None:
        """Unplug the host's module: its pty disappears, frames in flight are lost."""
        if count:
            self.air_down.note_disconnect()
        for pipe in self._pipes:
            await pipe.stop()
        self.down_buffer.clear()
        self.up_buffer.clear()
        self.port.close()

    async def reconnect(self) -> None:
        """Plug it back in behind the same symlink, with a fresh parser."""
        self._decoder = ApiFrameDecoder(escaped=self.escaped)
        self.port.open()
        for pipe in self._pipes:
            pipe.start()

    # ---- host → device ---------------------------------------------------------------------

    def _from_uart(self, data: bytes) -> None:
        """Host UART bytes arrive at the module's baud rate."""
        self._uart_in.push(data, len(data))

    def _on_uart(self, data: bytes) -> None:
        """Parse API frames out of the UART stream."""
        for frame_data in self._decoder.feed(data):
            if frame_data[0] == FrameType.TRANSMIT_REQUEST and len(frame_data) >= 14:
                self._transmit(TransmitRequest.parse(frame_data))
            else:
                self.counters.unknown_frames += 1

    def _transmit(self, request: TransmitRequest) -> None:
        """Send over the air with MAC retries, or answer at once with the failure."""
        self.counters.tx_requests += 1
        if len(request.data) > MAX_RF_PAYLOAD:
            self.counters.too_large += 1
            self._status(request.frame_id, 0, DeliveryStatus.PAYLOAD_TOO_LARGE)
            return
        if request.dest_addr64 != self.controller_addr64:
            # Nobody answers at that address: every MAC attempt goes unacknowledged.
            self.counters.wrong_address += 1
            self._status(request.frame_id, MAC_RETRIES, DeliveryStatus.MAC_ACK_FAILURE)
            return
        size = len(request.data)
        if not self.down_buffer.admit(size):
            # Its bytes overran the buffer: the module never saw a whole frame, so no status.
            self.counters.down_overflow += 1
            return
        attempts, data = _attempts(self.air_down, request.data)
        airtime = attempts * (size + AIR_OVERHEAD_BYTES)
        self.air_bytes += airtime
        if data is None:
            packet = _AirPacket(b"", request.frame_id, MAC_RETRIES)
            self.down_buffer.hold(size, self._air_down.push(packet, airtime))
            return
        packet = _AirPacket(data, request.frame_id, attempts - 1)
        delay_s = self.latency_s + self.air_down.delay_s()
        self.down_buffer.hold(size, self._air_down.push(packet, airtime, delay_s))

    def _arrive_device(self, packet: _AirPacket) -> None:
        """The air is done with a packet: hand it to the device and report to the host."""
        self.counters.retries += packet.retries
        if not packet.data:
            self.counters.failed += 1
            self._status(packet.frame_id, MAC_RETRIES, DeliveryStatus.MAC_ACK_FAILURE)
            return
        self.counters.delivered += 1
        self.endpoint.write(packet.data)
        self._status(packet.frame_id, packet.retries, DeliveryStatus.SUCCESS)

    def _status(self, frame_id: int, retries: int, delivery: int) -> None:
        """Transmit Status to the host, unless it asked for none (frame id 0)."""
        if frame_id:
            self._to_uart(TransmitStatus(frame_id, retries, delivery).frame_data())

    # ---- device → host ---------------------------------------------------------------------

    def _from_device(self, data: bytes) -> None:
        """The controller's module packetises whole frames from its UART."""
        for frame in self._splitter.feed(data):
            if not self.up_buffer.admit(len(frame)):
                self.counters.up_overflow += 1
                continue
            attempts, out = _attempts(self.air_up, frame)
            airtime = attempts * (len(frame) + AIR_OVERHEAD_BYTES)
            self.air_bytes += airtime
            if out is None:
                # Every attempt failed: the air was busy all the same, and nothing arrives.
                self.up_buffer.hold(len(frame), self._air_up.line.occupy(airtime / self._air_rate))
                self.counters.up_lost += 1
                continue
            delay_s = self.latency_s + self.air_up.delay_s()
            self.up_buffer.hold(len(frame), self._air_up.push(out, airtime, delay_s))

    def _arrive_host(self, data: bytes) -> None:
        """Receive Packet from the controller's module onto the host UART."""
        self.counters.rx_packets += 1
        self._to_uart(ReceivePacket(self.controller_addr64, data).frame_data())

    def _to_uart(self, frame_data: bytes) -> None:
        """Frame data → API frame → paced UART to the host."""
        frame = encode_api_frame(frame_data, self.escaped)
        self._uart_out.push(frame, len(frame))


def _attempts(air: FaultInjector, data: bytes) -> tuple[int, bytes | None]:
    """Try up to 1 + MAC_RETRIES times; a corrupted packet fails the MAC's FCS like a lost one."""
    for attempt in range(1, MAC_RETRIES + 2):
        out = air.transmit(data)
        if out == data:
            return attempt, out
    return MAC_RETRIES + 1, None
